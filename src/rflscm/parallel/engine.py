"""Where the work runs: in-process (one worker), a local Ray started on demand, or an existing Ray cluster.

ray is imported only when a command asks for more than one worker or for a cluster, so a plain install (and
``--workers 1``) never needs it.  A local Ray is kept small: ``num_cpus`` = the workers, a 200 MB object store,
no dashboard, workers' logs not forwarded.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import ModuleType

import typer

from rflscm.errors import ConfigError

OBJECT_STORE_BYTES = 200 * 1024**2

WorkersOption = typer.Option(
    1,
    "--workers",
    min=1,
    metavar="N",
    help="Worker processes (count): 1 runs in-process; N > 1 starts a local Ray with N CPUs (needs the ray extra of rflscm).",
)
RayAddressOption = typer.Option(
    None,
    "--ray-address",
    metavar="ADDR",
    help="Join this existing Ray cluster (host:port or 'auto') instead of starting one; --workers actors run there.",
)


@dataclass(frozen=True)
class Engine:
    """How many workers, and where: ``address`` None starts a local Ray when ``workers`` > 1."""

    workers: int = 1
    address: str | None = None

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ConfigError(f"--workers must be at least 1 (got {self.workers}).")

    @property
    def parallel(self) -> bool:
        """True when the work goes to Ray actors (more than one worker, or a cluster to join)."""
        return self.workers > 1 or self.address is not None


def import_ray() -> ModuleType:
    """ray, or one line saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "--workers > 1 and --ray-address need Ray: pip install 'rflscm[ray]' (ray==2.60.0)."
        ) from None
    return ray


@contextmanager
def ray_session(engine: Engine) -> Iterator[ModuleType]:
    """ray, initialised for ``engine`` (joined or started); a Ray this call started is shut down on exit."""
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        try:
            if engine.address is not None:
                ray.init(address=engine.address, log_to_driver=False)
            else:
                ray.init(
                    num_cpus=engine.workers,
                    object_store_memory=OBJECT_STORE_BYTES,
                    include_dashboard=False,
                    log_to_driver=False,
                    configure_logging=False,
                )
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"join the Ray cluster at {engine.address!r}" if engine.address else "start a local Ray"
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ConfigError(f"could not {where}: {first}") from None
        started = True
    try:
        yield ray
    except SystemError as exc:
        # a signal handler's exception (the CLI's interruption on Ctrl-C) raised while Ray waited in its C code
        # comes out as "SystemError: ... returned a result with an exception set", the real one as its cause:
        # raise the real one, so that an interruption is reported as one (exit 130), not as a traceback
        inner = exc.__cause__ or exc.__context__
        if inner is None or isinstance(inner, SystemError):
            raise
        raise inner from None
    finally:
        if started:
            ray.shutdown()
