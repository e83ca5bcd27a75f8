"""Evaluation (SPEC §5): protocols, metrics, the evaluate entry point and the report."""

from rflscm.eval.evaluate import Evaluation, evaluate, resolve_protocol, run_evaluation
from rflscm.eval.oracle import OracleModel
from rflscm.eval.protocols import (
    PROTOCOLS,
    AdjustProtocol,
    MultiFreqProtocol,
    TestSet,
    UnseenProtocol,
    fit_with_protocol,
    make_protocol,
    protocol_from_dict,
    protocol_to_dict,
    split_grids,
)

__all__ = [
    "PROTOCOLS",
    "AdjustProtocol",
    "Evaluation",
    "MultiFreqProtocol",
    "OracleModel",
    "TestSet",
    "UnseenProtocol",
    "evaluate",
    "fit_with_protocol",
    "make_protocol",
    "protocol_from_dict",
    "protocol_to_dict",
    "resolve_protocol",
    "run_evaluation",
    "split_grids",
]
