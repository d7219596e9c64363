"""Run settings of a transport: histories, batches, seed, physics, cut-offs, estimator, tally budget.

``physics``: ``"dose"`` (default) transports the electrons and positrons photons set in motion
(condensed history, :mod:`tetdose.transport.history._electron`) and scores the energy they
deposit: absorbed dose. ``"kerma"`` deposits every charged particle's energy where it is born
(collision kerma, the fast approximation of earlier versions, bit for bit). Electron and positron
sources need ``"dose"``. Cut-offs (kinetic energies): ``energy_cutoff_mev`` for photons (also
the bremsstrahlung production threshold k_c), ``electron_cutoff_mev`` for e± (also the δ-ray
production threshold Δ); ``max_energy_loss_fraction`` is the largest fraction of its energy an
electron may lose in one step (EGSnrc's ESTEPE). ``photon_splitting`` n follows every source
photon as n copies of weight 1/n and plays Russian roulette with the electrons they set in motion
(unbiased; :mod:`tetdose.transport.history._coupled`; dose mode only);
``splitting_scheme="follow"`` follows those electrons with weight 1/n instead and plays the
roulette with the secondary photons (XVMC's scheme); ``"repeat"`` splits every photon of weight
1 (not only the source photons) into n copies whose interaction sites are evenly spaced along its
ray, share one interaction and one electron track, sampled once and replayed from each copy's
site, scaled to the local medium (XVMC's splitting with electron history repetition;
:mod:`tetdose.transport.history._split`, :mod:`tetdose.transport.history._repeat`);
``secondary_photon_splitting`` n₂ ≤ n splits the photons of weight 1 after the source photon
(the scattered photon kept, bremsstrahlung and annihilation photons of unweighted e±) into n₂
copies instead (None: n). ``range_rejection_mev``
E: an electron of at most E starting in a voxel or tet it cannot leave deposits its energy there
at once (EGSnrc's ESAVE; only the hard bremsstrahlung it would have radiated stays too; 0: off).
The estimator is ``"track_length"`` (kerma default) or ``"analog"``; dose mode scores the analog
energy deposition only. ``photon_tracking``: dose mode moves photons through the mesh (and
through the grid of a voxel-only world) by Woodcock (delta) tracking (``"woodcock"``, default:
a majorant, point location, no tet or voxel walk; :mod:`tetdose.transport.history._delta`) or
walks them cell by cell as kerma mode does (``"walk"``); both give the same dose within
statistics (different random numbers). Kerma mode always walks (its track-length estimator
needs every segment). ``quasi_random``: the source particles' position (or direction),
spectrum line and beam come from randomized Sobol points, independently scrambled per batch
(:mod:`tetdose.transport.sources.quasi`), and with ``"repeat"`` the source photon's split its
copies' offset and its shared Compton scatter and azimuth; off: bit for bit the pseudo-random
sources.
"""

from __future__ import annotations

from dataclasses import dataclass

from tetdose.errors import PlanError

#: The one spelling of each dose estimator (`--estimator`).
ESTIMATORS = ("analog", "track_length")
#: What a target uncertainty is about (`--target-statistic`): the relative σ of the structure's
#: mean dose, or the median of its cells' relative σ.
TARGET_STATISTICS = ("mean", "median")
#: The one spelling of each physics model (`--physics`).
PHYSICS = ("dose", "kerma")
#: How dose mode moves photons through the mesh: Woodcock (delta) tracking or the tet walk.
PHOTON_TRACKING = ("woodcock", "walk")
#: Defaults of the electron settings (cut-off [MeV], ESTEPE).
ELECTRON_CUTOFF_MEV = 0.2
MAX_ENERGY_LOSS_FRACTION = 0.25
#: What the dose is reported in (`--dose-to`): the medium (D_m, as transported) or water (D_w).
DOSE_TO = ("medium", "water")
#: Default photon splitting of dose mode (copies of each source photon).
PHOTON_SPLITTING = 1
#: What splitting does with the electrons of split photons: Russian roulette (survivors weight
#: 1; EGSnrc/ompMC), follow them all with weight 1/n (secondary photons rouletted; XVMC), or
#: that with one electron track replayed for every copy (XVMC's history repetition). The order
#: is the kernels' code (tetdose.transport.history._coupled).
SPLITTING_SCHEMES = ("roulette", "follow", "repeat")
#: Default largest electron energy of range rejection [MeV] (0: off).
RANGE_REJECTION_MEV = 1.0
#: Largest tally (n_batches × n_cells × 8 bytes) accepted by default.
MAX_TALLY_BYTES = 2 * 1024**3


@dataclass(frozen=True)
class TransportSettings:
    """Run settings: histories, batches (for the uncertainty), seed, photon cut-off [MeV],
    estimator (``None``: track_length for kerma, analog for dose), physics, electron cut-off
    [MeV], largest energy-loss fraction per electron step (module docstring)."""

    n_histories: int
    n_batches: int = 10
    seed: int = 1
    energy_cutoff_mev: float = 0.01
    estimator: str | None = None
    stream: int = 0
    max_tally_bytes: int = MAX_TALLY_BYTES
    #: Stop once the relative standard error of the mean dose in ``target_region`` is at most this
    #: (e.g. 0.01); ``n_histories`` is then the cap. None: run every history.
    target_uncertainty: float | None = None
    #: Structure of the target (a plan [regions] name or a label); None: the prescription's.
    target_region: str | int | None = None
    #: "mean": σ of the structure's mean dose; "median": median σ/D of its cells (tets, voxels).
    target_statistic: str = "mean"
    physics: str = "dose"
    electron_cutoff_mev: float = ELECTRON_CUTOFF_MEV
    max_energy_loss_fraction: float = MAX_ENERGY_LOSS_FRACTION
    #: Copies of each source photon (weight 1/n each, electron Russian roulette); 1: none.
    photon_splitting: int = PHOTON_SPLITTING
    #: Electrons of split photons: "roulette", "follow" (weight 1/n) or "repeat" (one replayed
    #: track, weight 1/n).
    splitting_scheme: str = "roulette"
    #: With "repeat": copies of every photon of weight 1 after the source photon (1 ≤ n₂ ≤
    #: photon_splitting); None: photon_splitting.
    secondary_photon_splitting: int | None = None
    #: Range rejection below this electron energy [MeV] in cells it cannot leave; 0: off.
    range_rejection_mev: float = RANGE_REJECTION_MEV
    #: Dose mode's photon flights through the mesh: "woodcock" (delta tracking) or "walk".
    photon_tracking: str = "woodcock"
    #: "medium" (D_m) or "water" (D_w = D_m · s_w,m per cell, :mod:`tetdose.transport.run.water`).
    dose_to: str = "medium"
    #: Source particles from scrambled Sobol points (one independent scramble per batch).
    quasi_random: bool = False

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
        if self.physics not in PHYSICS:
            raise PlanError(f"physics {self.physics!r} is unknown; use one of {PHYSICS}")
        if self.estimator is None:
            object.__setattr__(self, "estimator",
                               "analog" if self.physics == "dose" else "track_length")
        if self.estimator not in ESTIMATORS:
            raise PlanError(f"estimator {self.estimator!r} is unknown; use one of {ESTIMATORS}")
        if self.target_uncertainty is not None and not 0.0 < self.target_uncertainty < 1.0:
            raise PlanError(f"target_uncertainty is a relative standard error in (0, 1), e.g. "
                            f"0.01 for 1 %; got {self.target_uncertainty}")
        if self.target_statistic not in TARGET_STATISTICS:
            raise PlanError(f"target_statistic {self.target_statistic!r} is unknown; use one of "
                            f"{TARGET_STATISTICS}")
        if self.physics == "dose" and self.estimator != "analog":
            raise PlanError("physics 'dose' scores the energy electrons deposit (the analog "
                            "estimator); the track-length estimator gives kerma: use "
                            "physics='kerma' with it")
        if not 0.001 <= self.electron_cutoff_mev < 20.0:
            raise PlanError(f"electron_cutoff_mev must lie in [0.001, 20) MeV, got "
                            f"{self.electron_cutoff_mev}")
        if not 0.0 < self.max_energy_loss_fraction <= 0.5:
            raise PlanError(f"max_energy_loss_fraction must lie in (0, 0.5], got "
                            f"{self.max_energy_loss_fraction} (0.25 is EGSnrc's default)")
        if not 1 <= int(self.photon_splitting) <= 1000:
            raise PlanError(f"photon_splitting must be an integer in [1, 1000] (1 = none), got "
                            f"{self.photon_splitting}")
        n2 = self.secondary_photon_splitting
        if n2 is not None and not 1 <= int(n2) <= int(self.photon_splitting):
            raise PlanError(f"secondary_photon_splitting must be an integer in [1, "
                            f"photon_splitting = {self.photon_splitting}], got {n2}")
        if n2 is not None and self.splitting_scheme != "repeat":
            raise PlanError("secondary_photon_splitting splits the photons after the source "
                            "photon along their ray: it needs splitting_scheme='repeat'")
        if self.dose_to not in DOSE_TO:
            raise PlanError(f"dose_to {self.dose_to!r} is unknown; use one of {DOSE_TO}")
        if self.dose_to == "water" and self.physics != "dose":
            raise PlanError("dose to water converts absorbed dose by stopping-power ratios; "
                            "use physics='dose' with dose_to='water' (kerma is in the medium)")
        if self.splitting_scheme not in SPLITTING_SCHEMES:
            raise PlanError(f"splitting_scheme {self.splitting_scheme!r} is unknown; use one of "
                            f"{SPLITTING_SCHEMES}")
        if not 0.0 <= self.range_rejection_mev <= 20.0:
            raise PlanError(f"range_rejection_mev must lie in [0, 20] MeV (0 = off), got "
                            f"{self.range_rejection_mev}")
        if self.photon_tracking not in PHOTON_TRACKING:
            raise PlanError(f"photon_tracking {self.photon_tracking!r} is unknown; use one of "
                            f"{PHOTON_TRACKING}")
        object.__setattr__(self, "range_rejection_mev", float(self.range_rejection_mev))
        for name in ("n_histories", "n_batches", "seed", "stream", "photon_splitting"):
            object.__setattr__(self, name, int(getattr(self, name)))
        if n2 is not None:
            object.__setattr__(self, "secondary_photon_splitting", int(n2))

    @property
    def secondary_copies(self) -> int:
        """Copies of a photon of weight 1 after the source photon (the kernels' n₂)."""
        return self.secondary_photon_splitting or self.photon_splitting

    def check_tally_size(self, n_cells: int) -> None:
        water = self.dose_to == "water" and self.physics == "dose"  # + its two sums per cell
        need = self.n_batches * n_cells * 8 * (3 if water else 1)
        if need > self.max_tally_bytes:
            raise PlanError(f"the tally needs {need / 2**20:.0f} MiB ({self.n_batches} batches × "
                            f"{n_cells} cells{' × 3 for dose to water' if water else ''}); use "
                            "fewer batches or raise max_tally_bytes")
