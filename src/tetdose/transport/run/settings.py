"""Run settings of a transport: histories, batches, seed, cut-off, estimator, tally budget."""

from __future__ import annotations

from dataclasses import dataclass

from tetdose.errors import PlanError

#: The one spelling of each dose estimator (`--estimator`).
ESTIMATORS = ("analog", "track_length")
#: Largest tally (n_batches × n_cells × 8 bytes) accepted by default.
MAX_TALLY_BYTES = 2 * 1024**3


@dataclass(frozen=True)
class TransportSettings:
    """Run settings: histories, batches (for the uncertainty), seed, cut-off [MeV], estimator."""

    n_histories: int
    n_batches: int = 10
    seed: int = 1
    energy_cutoff_mev: float = 0.01
    estimator: str = "track_length"
    stream: int = 0
    max_tally_bytes: int = MAX_TALLY_BYTES
    #: Stop once the relative standard error of the mean dose in ``target_region`` is at most this
    #: (e.g. 0.01); ``n_histories`` is then the cap. None: run every history.
    target_uncertainty: float | None = None
    #: Structure of the target (a plan [regions] name or a label); None: the prescription's.
    target_region: str | int | None = None

    def __post_init__(self) -> None:
        if int(self.n_batches) < 2:
            raise PlanError("n_batches must be at least 2 (batch statistics give the uncertainty)")
        if int(self.n_histories) < int(self.n_batches):
            raise PlanError(f"n_histories ({self.n_histories}) must be at least n_batches "
                            f"({self.n_batches})")
        if int(self.seed) < 0 or int(self.stream) < 0:
            raise PlanError("seed and stream must be non-negative integers")
        if not 0.0 < self.energy_cutoff_mev < 20.0:
            raise PlanError(f"energy_cutoff_mev must lie in (0, 20) MeV, got "
                            f"{self.energy_cutoff_mev}")
        if self.estimator not in ESTIMATORS:
            raise PlanError(f"estimator {self.estimator!r} is unknown; use one of {ESTIMATORS}")
        if self.target_uncertainty is not None and not 0.0 < self.target_uncertainty < 1.0:
            raise PlanError(f"target_uncertainty is a relative standard error in (0, 1), e.g. "
                            f"0.01 for 1 %; got {self.target_uncertainty}")
        for name in ("n_histories", "n_batches", "seed", "stream"):
            object.__setattr__(self, name, int(getattr(self, name)))

    def check_tally_size(self, n_cells: int) -> None:
        need = self.n_batches * n_cells * 8
        if need > self.max_tally_bytes:
            raise PlanError(f"the tally needs {need / 2**20:.0f} MiB ({self.n_batches} batches × "
                            f"{n_cells} cells); use fewer batches or raise max_tally_bytes")
