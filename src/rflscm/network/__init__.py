"""Network optimisation on a learned channel model (issue 13): KPIs, search space, search, truth check.

Evaluation level (STYLE.md layering): it uses the model contract and the scenario/antenna APIs, and
— like :mod:`rflscm.eval` — may read ``truth/`` to verify a recommendation.
"""

from rflscm.network.kpi import KPIConfig, grid_maps, network_kpis

__all__ = ["KPIConfig", "grid_maps", "network_kpis"]
