"""ompmc as a dose engine: EGSnrc coupled photon–electron transport on tetdose's voxel world.

`ompmc <https://github.com/e0404/ompMC>`_ (E. Doerner, P. Caprile, Med. Phys. 44 (2017) 6672;
pip package, GPL-3, optional extra ``tetdose[ompmc]``) is a C port of EGSnrc's condensed-history
transport on rectilinear voxel grids: PEGS4 media, Møller, Bhabha, bremsstrahlung, annihilation,
multiple scattering, Compton / Rayleigh / photoelectric / pair from XCOM, Woodcock tracking of
photons. :func:`simulate_ompmc` runs it on a density image and returns a :class:`DoseResult` in
the conventions of tetdose's engine, so ``compare``, accumulation, prescriptions and RT Dose work
unchanged.

**Geometry.** The image's voxels in the grid frame q = Dᵀ(p − origin) (:mod:`tetdose.core.image`),
bounds ``(i − ½)·spacing`` converted to cm; densities as given [g/cm³]; voxels of density 0 are
vacuum (ompmc would give a medium its PEGS density there). Outside the grid is vacuum, as in
tetdose's voxel world.

**Media.** Every voxel gets the material tetdose would give it (region label → the plan's
``[materials]``, else its density class, :func:`tetdose.transport.run.job.assign_materials`). ompmc
knows only the media of its PEGS4 file, so each tetdose material is run as the PEGS medium nearest to
it: the largest of the |ln(μ/ρ)| differences over 0.1–3 MeV (:data:`COMPARE_ENERGIES_MEV`;
incoherent + photoelectric + pair, tetdose's own tables of both compositions,
:mod:`tetdose.transport.physics.xs`) and of the electrons per gram (∝ Z/A, which scales Compton
scattering and the collision stopping power), plus :data:`DENSITY_WEIGHT` per e-fold between
the medium's nominal density and the mean density of the voxels that use it, is smallest. The
run record names each choice and its deviations (e.g. adipose → H2O521ICRU, 0.35 %).
``OmpmcOptions.media`` overrides a choice; a PEGS file made with EGSnrc's PEGS4 for the exact
compositions is ``OmpmcOptions.pegs``.

**Source.** Nothing is approximated: tetdose draws the source particles with its own sampler and
its own random streams (:func:`tetdose.transport.sources.particles.source_particles`, the particles
its engine would start, bit for bit: pencil, parallel, point, linac with jaws and MLC, arcs and
VMAT), writes them as an IAEA phase space (:mod:`.iaea_phsp`) and ompmc replays it, one particle
per history, each carried in a straight line to the grid (ompmc's ``calc_forward_phsp``).

**Batches and statistics.** tetdose batch b (histories ``[b·N//B, (b+1)·N//B)``) is one ompmc
run with its own Philox key (from :func:`tetdose._random.seed_for` of seed, stream, b) on those
histories' particles, padded to an even count with a weightless particle that misses the grid
(ompmc runs two internal batches of equal size). Its result, the mean energy per history in each
voxel [MeV] (``output_dose=False``: tetdose's masses), times the histories
is row b of ``energy_per_batch_mev``: dose and σ follow from the batches as for tetdose's tallies
(:mod:`tetdose.transport.history.result`). Ledger per batch: source = the particles' energy,
deposited = the voxels' energy (below-cut-off electrons and photons deposit locally in ompmc),
escaped = source − deposited (particles that miss the grid included, counted as
``missed_world``).

**Low densities.** ompmc scores no energy in voxels below
:data:`UNSCORED_BELOW_G_CM3` (measured on 2 MeV photons through water with 2 mm layers of
0.020–0.1 g/cm³: nothing at 0.042 g/cm³ and below, 90–100 % of tetdose's dose from 0.044 on,
whatever PEGS medium the voxels get; tests/unit/test_coupling_ompmc.py). Such voxels (airways,
the air around the patient) get zero dose from this engine; the run warns and records how many
non-empty voxels that is (``unscored_voxels``). tetdose's own engine scores every voxel.

**Cut-offs.** Electrons are followed down to ``electron_cutoff_mev`` kinetic (ECUT = that + m_e c²;
at least the PEGS file's AE: 10 keV with ``521icru``, 189 keV with ``700icru``), photons to
``photon_cutoff_mev`` (PCUT, at least AP = 10 keV). ``n_split`` is ompmc's photon splitting
(unbiased; 20 by default as in ompmc).
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import re
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import numba
import numpy as np
from tqdm.auto import tqdm

from tetdose._constants import MM3_PER_CM3, MM_PER_CM
from tetdose._optional import import_optional
from tetdose._random import seed_for
from tetdose._typing import FloatArray, IntArray
from tetdose._version import __version__
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image, ImageGrid
from tetdose.core.mesh import TetMesh
from tetdose.coupling.iaea_phsp import ELECTRON, PHOTON, POSITRON, write_phase_space
from tetdose.coupling.onto_mesh import result_onto_mesh, voxel_share
from tetdose.errors import DensityError, OptionError, PlanError, TetdoseError
from tetdose.plan.model import Plan
from tetdose.transport import World, resolved_target, target_cells
from tetdose.transport.history.result import DoseResult
from tetdose.transport.physics.materials import MATERIALS, Material, library_hint
from tetdose.transport.physics.xs import ELECTRON_MASS_MEV, mass_coefficients
from tetdose.transport.run.job import (
    MIN_TARGET_BATCHES,
    PROGRESS_DELAY_S,
    assign_materials,
    plan_media,
    warn_target_missed,
)
from tetdose.transport.run.settings import TransportSettings
from tetdose.transport.run.water import water_factors
from tetdose.transport.sources.particles import source_particles

#: PEGS4 files shipped in the ompmc wheel (AE = 0.521 / 0.700 MeV total electron energy).
SHIPPED_PEGS = ("521icru", "700icru")
#: Photon energies [MeV] at which media are compared for the nearest PEGS medium: 0.1–3 MeV,
#: where Compton scattering makes the dose of megavoltage beams (mean photon energy of a 6 MV
#: beam ≈ 1.6 MeV, of its phantom-scattered photons lower). Photoelectric absorption below and
#: pair production above weigh little in the dose of such beams but would pick, e.g., nylon over
#: water for adipose (water: within 0.3 % up to 3 MeV, 4.7 % at 13 MeV where pair production
#: rises with Z).
COMPARE_ENERGIES_MEV = np.geomspace(0.1, 3.0, 30)
#: Weight of the density mismatch in the choice of a PEGS medium, per e-fold of ρ_PEGS/ρ: PEGS4
#: computes the density-effect correction of the collision stopping power at the medium's
#: nominal density, and it is worth ~1.2 % of the stopping power of 1 MeV electrons in water
#: between ρ → 0 and 1 g/cm³ (δ ≈ 0.24 against a stopping number ≈ 19, ICRU Report 37).
DENSITY_WEIGHT = 0.01
#: Largest number of media one ompmc geometry may hold (ompmc's MXMED).
MAX_MEDIA = 9
#: Density [g/cm³] below which ompmc scores no energy in a voxel (module docstring).
UNSCORED_BELOW_G_CM3 = 0.0435
#: Histories of the pilot run that checks the beams reach the grid.
PILOT_HISTORIES = 200
#: Lines of ompmc's own output shown when a run fails.
LOG_TAIL_LINES = 12


@dataclass(frozen=True)
class OmpmcOptions:
    """Physics options of an ompmc run (module docstring): the PEGS4 file (``"521icru"``,
    ``"700icru"`` or a path), cut-offs as kinetic energies [MeV] (``photon_cutoff_mev=None``:
    the settings' ``energy_cutoff_mev``), photon splitting, tetdose material → PEGS medium
    overrides, OpenMP threads (None: numba's thread count)."""

    pegs: str = "521icru"
    electron_cutoff_mev: float = 0.01
    photon_cutoff_mev: float | None = None
    n_split: int = 20
    media: Mapping[str, str] = field(default_factory=dict)
    threads: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.electron_cutoff_mev < 20.0:
            raise OptionError(f"electron_cutoff_mev must lie in (0, 20) MeV (kinetic), got "
                              f"{self.electron_cutoff_mev}")
        if self.photon_cutoff_mev is not None and not 0.0 < self.photon_cutoff_mev < 20.0:
            raise OptionError(f"photon_cutoff_mev must lie in (0, 20) MeV, got "
                              f"{self.photon_cutoff_mev}")
        if int(self.n_split) < 1:
            raise OptionError(f"n_split must be at least 1 (1 = no photon splitting), got "
                              f"{self.n_split}")
        if self.threads is not None and int(self.threads) < 1:
            raise OptionError(f"threads must be at least 1, got {self.threads}")


class PegsMedium(NamedTuple):
    """A medium of a PEGS4 file: name, nominal density [g/cm³], composition, electron (AE) and
    photon (AP) production thresholds [MeV, AE total energy], upper energies UE, UP [MeV]."""

    name: str
    density_g_cm3: float
    material: Material
    ae_mev: float
    ap_mev: float
    ue_mev: float
    up_mev: float


class MediumChoice(NamedTuple):
    """The PEGS medium run for a tetdose material, and how far its photon attenuation (largest
    |Δ ln μ/ρ|, 0.1–3 MeV) and electrons per mass (Z/A) are from the material's."""

    pegs: str
    photon_deviation: float
    z_over_a_deviation: float
    chosen_by: str  # "nearest" | "user"


def ompmc_module() -> ModuleType:
    """The ``ompmc`` package, or a TetdoseError that says to install ``tetdose[ompmc]``."""
    return import_optional("ompmc", "ompmc", "the ompmc engine (--engine ompmc)")


def pegs_path(pegs: str) -> Path:
    """The PEGS4 data file of ``pegs``: a shipped name (:data:`SHIPPED_PEGS`) or a path."""
    if pegs in SHIPPED_PEGS:
        return Path(ompmc_module().data_path()) / "pegs4" / f"{pegs}.pegs4dat"
    path = Path(pegs)
    if not path.is_file():
        raise OptionError(f"PEGS4 file {pegs!r} not found; give {' or '.join(SHIPPED_PEGS)} "
                          "(shipped with ompmc) or the path of a .pegs4dat file")
    return path


_MEDIUM = re.compile(r"^\s*MEDIUM=\s*([^\s,]+)")
_RHO = re.compile(r"RHO=\s*([-+0-9.Ee]+)\s*,\s*NE=\s*(\d+)")
_ELEMENT = re.compile(r"Z=\s*([0-9.]+)\s*,\s*A=\s*([0-9.]+)\s*,\s*PZ=\s*([-+0-9.Ee]+)\s*,"
                      r"\s*RHOZ=\s*([-+0-9.Ee]+)")


@lru_cache(maxsize=4)
def pegs_media(path: Path) -> dict[str, PegsMedium]:
    """Media of a PEGS4 file by name: composition from its element lines (mass fractions
    ∝ RHOZ = PZ·A), then the line RLC, AE, AP, UE, UP."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise OptionError(f"cannot read PEGS4 file {path}: {exc.strerror}") from exc
    media: dict[str, PegsMedium] = {}
    for i, line in enumerate(lines):
        m = _MEDIUM.match(line)
        if not m or i + 1 >= len(lines):
            continue
        rho = _RHO.search(lines[i + 1])
        if rho is None:
            continue
        n_el = int(rho.group(2))
        elements = [_ELEMENT.search(lines[i + 2 + k]) for k in range(n_el)]
        if any(e is None for e in elements):
            continue
        fractions = np.array([float(e.group(4)) for e in elements])  # type: ignore[union-attr]
        zs = [round(float(e.group(1))) for e in elements]  # type: ignore[union-attr]
        try:
            rlc, ae, ap, ue, up = (float(v) for v in lines[i + 2 + n_el].split()[:5])
        except (IndexError, ValueError):
            continue
        name = m.group(1)
        material = Material(name, tuple(zip(zs, (fractions / fractions.sum()).tolist(),
                                            strict=True)), float(rho.group(1)), str(path.name))
        media[name] = PegsMedium(name, float(rho.group(1)), material, ae, ap, ue, up)
    if not media:
        raise OptionError(f"{path} holds no PEGS4 medium (MEDIUM= blocks); give a PEGS4 data "
                          "file such as ompmc's 521icru.pegs4dat")
    return media


def _coefficients(material: Material) -> tuple[FloatArray, float]:
    """(μ/ρ without coherent scattering [cm²/g] at :data:`COMPARE_ENERGIES_MEV`, incoherent μ/ρ
    at 2 MeV, which is N_A·(Z/A)·σ_KN to within binding effects: electrons per gram)."""
    mu, _ = mass_coefficients(material, np.append(COMPARE_ENERGIES_MEV, 2.0))
    return mu[:-1, 1:].sum(axis=1), float(mu[-1, 1])


@lru_cache(maxsize=64)
def _choose(target: Material, pegs: Path, override: str | None, density_g_cm3: float
            ) -> MediumChoice:
    media = pegs_media(pegs)
    name = target.name
    mu_t, electrons_t = _coefficients(target)

    def deviations(medium: str) -> tuple[float, float]:
        mu, electrons = _coefficients(media[medium].material)
        return float(np.abs(np.log(mu / mu_t)).max()), abs(electrons / electrons_t - 1.0)

    if override is not None:
        if override not in media:
            raise PlanError(f"PEGS medium {override!r} (for {name!r}) is not in {pegs.name}; "
                            f"it has {', '.join(sorted(media))}")
        return MediumChoice(override, *deviations(override), "user")
    scored = []
    for medium in media:
        try:
            photon, electrons = deviations(medium)
        except PlanError:  # an element outside the photon tables: not a candidate
            continue
        density_term = DENSITY_WEIGHT * abs(math.log(media[medium].density_g_cm3 / density_g_cm3))
        scored.append((max(photon, electrons) + density_term, medium, photon, electrons))
    _, best, photon, electrons = min(scored)
    return MediumChoice(best, photon, electrons, "nearest")


def choose_media(names: list[str], options: OmpmcOptions,
                 density_g_cm3: Mapping[str, float] | None = None,
                 compositions: Mapping[str, Material] | None = None) -> dict[str, MediumChoice]:
    """The PEGS medium run for each tetdose material name (a built-in name or one of
    ``compositions``, the plan's ``[materials.NAME]``), used at the typical density
    ``density_g_cm3[name]`` (default: the material's nominal density) (module docstring)."""
    pegs = pegs_path(options.pegs)
    known = dict(MATERIALS) | dict(compositions or {})
    unknown = [n for n in names if n not in known]
    if unknown:
        raise PlanError(f"material {unknown[0]!r} has no composition in tetdose; "
                        f"{library_hint(unknown[0])} or define it as [materials.{unknown[0]}]")
    typical = {n: known[n].density_g_cm3 for n in names} | dict(density_g_cm3 or {})
    # two significant digits: phases of one study share the choice (and its cache entry)
    return {n: _choose(known[n], pegs, options.media.get(n),
                       float(f"{max(typical[n], 1e-6):.2g}")) for n in names}


class OmpmcWorld(NamedTuple):
    """The voxel world as ompmc takes it (cm, (nx, ny, nz) Fortran-ordered cubes)."""

    bounds_cm: tuple[FloatArray, FloatArray, FloatArray]
    media: list[str]  # PEGS names, material index i + 1
    density: FloatArray  # (nx, ny, nz) F order [g/cm³]
    material: IntArray  # (nx, ny, nz) F order int32, 0 = vacuum
    mass_g: FloatArray  # (V,) voxel masses, flat voxel order
    choices: dict[str, MediumChoice]
    cell_material: IntArray  # (V,) tetdose material per voxel: index into list(choices)


def ompmc_world(density: Image, plan: Plan, options: OmpmcOptions,
                labels: Image | None = None) -> OmpmcWorld:
    """Bounds, media and cubes of ``density`` [g/cm³] for ompmc (module docstring)."""
    grid = density.grid
    rho = np.asarray(density.array, dtype=np.float64)
    if not np.all(np.isfinite(rho)) or rho.min() < 0.0:
        raise DensityError("the density image has NaN, infinite or negative values; fix the CT "
                           "or its calibration")
    if labels is not None:
        grid.require_same(labels.grid, "the density and the label image")
    region = None if labels is None else np.asarray(labels.array).ravel().astype(np.int64)
    mat, names = assign_materials(rho.ravel(), region, plan)
    flat = rho.ravel()
    typical = {n: float(np.average(flat[mat == i], weights=flat[mat == i]))
               for i, n in enumerate(names) if flat[mat == i].sum() > 0}
    choices = choose_media(names, options, typical, plan.compositions)
    pegs_names = sorted({c.pegs for c in choices.values()})
    if len(pegs_names) > MAX_MEDIA:
        raise PlanError(f"ompmc holds at most {MAX_MEDIA} media, this world needs "
                        f"{len(pegs_names)} ({', '.join(pegs_names)}); merge [materials]")
    index = np.array([pegs_names.index(choices[n].pegs) + 1 for n in names], dtype=np.int32)
    medium = np.where(rho.ravel() > 0.0, index[mat], 0).astype(np.int32)
    nz, ny, nx = grid.shape
    bounds = tuple((np.arange(n + 1) - 0.5) * s / MM_PER_CM
                   for n, s in zip((nx, ny, nz), grid.spacing_mm, strict=True))
    # (nz, ny, nx) C order is (nx, ny, nz) Fortran order: the same memory, no copy.
    return OmpmcWorld(bounds, pegs_names, np.ascontiguousarray(rho).T,  # type: ignore[arg-type]
                      np.ascontiguousarray(medium.reshape(grid.shape)).T,
                      rho.ravel() * grid.voxel_volume_mm3 / MM3_PER_CM3, choices, mat)


def _cutoffs(options: OmpmcOptions, settings: TransportSettings, media: list[str],
             pegs: Path) -> tuple[float, float]:
    """(ECUT total, PCUT) [MeV] checked against the PEGS file's AE and AP."""
    table = pegs_media(pegs)
    ae = max(table[m].ae_mev for m in media)
    ap = max(table[m].ap_mev for m in media)
    ecut = options.electron_cutoff_mev + ELECTRON_MASS_MEV
    pcut = options.photon_cutoff_mev if options.photon_cutoff_mev is not None else \
        settings.energy_cutoff_mev
    if ecut < ae - 1e-3:  # PEGS files round AE: 0.521 MeV is "10 keV"
        raise OptionError(f"the electron cut-off {options.electron_cutoff_mev:g} MeV is below "
                          f"what {pegs.name} was made for (AE = {ae:g} MeV total, "
                          f"{ae - ELECTRON_MASS_MEV:.3g} MeV kinetic); raise it or use "
                          "pegs='521icru' (10 keV)")
    if pcut < ap - 1e-9:
        raise OptionError(f"the photon cut-off {pcut:g} MeV is below {pegs.name}'s AP = {ap:g} "
                          "MeV; raise it")
    return max(ecut, ae), max(pcut, ap)


def _gomp_library(module: ModuleType) -> ctypes.CDLL | None:
    """The OpenMP runtime ompmc runs on (its wheel bundles one), or None."""
    libs = Path(module.__file__).resolve().parent.parent / "ompmc.libs"
    for path in sorted(libs.glob("libgomp*")):
        return ctypes.CDLL(str(path))
    with contextlib.suppress(OSError):
        return ctypes.CDLL("libgomp.so.1")
    return None


def set_threads(module: ModuleType, threads: int) -> bool:
    """Set ompmc's OpenMP thread count (``omp_set_num_threads``); False if it cannot be set."""
    lib = _gomp_library(module)
    if lib is None:
        return False
    lib.omp_set_num_threads(ctypes.c_int(int(threads)))
    return True


@contextlib.contextmanager
def captured_output() -> Iterator[Any]:
    """Redirect the process's stdout and stderr (fds 1 and 2, where ompmc's C code prints) into
    a temporary file for the duration; yields the file (read it for the log)."""
    sys.stdout.flush()
    sys.stderr.flush()
    libc = ctypes.CDLL(None)
    with tempfile.TemporaryFile() as log:
        saved = os.dup(1), os.dup(2)
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            yield log
        finally:
            libc.fflush(None)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _log_tail(log: Any) -> str:  # noqa: ANN401 - a file object
    log.seek(0)
    lines = log.read().decode(errors="replace").splitlines()
    return " | ".join(ln.strip() for ln in lines[-LOG_TAIL_LINES:] if ln.strip())


def _key(seed: int, stream: int, batch: int) -> tuple[int, int]:
    """Philox key of ompmc run ``batch``: two 31-bit words of seed_for(seed, stream, batch)."""
    z = int(seed_for(seed, stream, batch))
    return z & 0x7FFFFFFF, (z >> 31) & 0x7FFFFFFF


def _batch_bounds(settings: TransportSettings) -> IntArray:
    return np.arange(settings.n_batches + 1) * settings.n_histories // settings.n_batches


class _Engine(NamedTuple):
    module: ModuleType
    geometry: Any
    grid: ImageGrid
    physics: dict[str, Any]
    workdir: Path


#: IAEA particle code of each source particle name.
_IAEA_CODES = {"photon": PHOTON, "electron": ELECTRON, "positron": POSITRON}


def iaea_particle(plan: Plan) -> int:
    """IAEA type code of the plan's source particles (photons, electrons or positrons: one kind;
    the phase space is written with it, so ompmc transports electron beams as electrons)."""
    kinds = {str(getattr(s, "particle", "photon")) for s in plan.sources}
    if len(kinds) != 1:
        raise PlanError(f"an ompmc run needs beams of one particle, this plan has {sorted(kinds)}; "
                        "run each particle's beams as a plan of its own and add the doses")
    return _IAEA_CODES[kinds.pop()]


def _run_batch(eng: _Engine, plan: Plan, settings: TransportSettings, b: int, first: int,
               count: int) -> tuple[FloatArray, FloatArray, IntArray]:
    """(energy per voxel [MeV], ledger row, counter row) of histories first … first+count−1."""
    grid = eng.grid

    def to_frame(a: FloatArray, is_dir: bool) -> FloatArray:
        return a @ grid.direction if is_dir else grid.to_grid_frame(a)

    p = source_particles(plan, settings, first, count, to_frame)
    pos_cm, direction, energy = p.position_mm / MM_PER_CM, p.direction, p.energy_mev
    weight = np.ones(count)
    n_run = count + count % 2
    if n_run > count:  # a weightless particle outside the grid, flying away from it
        pos_cm = np.vstack([pos_cm, [[-1e6, -1e6, -1e6]]])
        direction = np.vstack([direction, [[0.0, 0.0, -1.0]]])
        energy = np.append(energy, energy[0])
        weight = np.append(weight, 0.0)
    base = eng.workdir / f"batch{b}"
    write_phase_space(base, energy, pos_cm, direction, weight, iaea_particle(plan), scratch=True)
    om = eng.module
    physics = om.Physics(**eng.physics, seeds=_key(settings.seed, settings.stream, b))
    with captured_output() as log:
        try:
            mean, _, summary = om.calc_forward_phsp(
                eng.geometry, om.PhaseSpaceSource(str(base)), physics, n_histories=n_run,
                n_batches=2, output_dose=False)
        except (RuntimeError, ValueError) as exc:
            raise TetdoseError(f"ompmc failed: {exc} (its log: {_log_tail(log)})") from exc
    if summary.n_histories != n_run:
        raise TetdoseError(f"ompmc ran {summary.n_histories} histories of {n_run}; "
                           "report this with the ompmc version")
    e_vox = np.asarray(mean, dtype=np.float64).ravel(order="F") * n_run
    source = float(p.energy_mev.sum())
    deposited = float(e_vox.sum())
    ledger = np.array([source, deposited, source - deposited, 0.0, 0.0])
    counts = np.zeros(7, dtype=np.int64)
    counts[6] = count - summary.n_started  # the padding particle never starts
    return e_vox, ledger, counts


def simulate_ompmc(density: Image, plan: Plan, settings: TransportSettings, *,
                   calibration: HUCalibration | None = None, labels: Image | None = None,
                   options: OmpmcOptions | None = None, mesh: TetMesh | None = None,
                   progress: bool | None = None) -> DoseResult:
    """Dose per voxel of ``plan`` on ``density`` [g/cm³] (or a CT in HU with ``calibration``),
    computed by ompmc (module docstring); per source particle like tetdose's engine
    (``plan.particles`` normalization). With ``mesh``, the voxel energy put on its tets
    (:func:`tetdose.coupling.onto_mesh.result_onto_mesh`): a mesh result.

    ``settings.target_uncertainty`` stops the run, as tetdose's engine does, once the mean dose
    of the target region (the tets of ``mesh`` holding it, else its voxels in ``labels``) has
    that relative standard error, after at least :data:`MIN_TARGET_BATCHES` batches.
    """
    if mesh is not None:
        return simulate_ompmc_on_mesh(density, mesh, plan, settings, calibration=calibration,
                                      labels=labels, options=options, progress=progress)[0]
    return _simulate(density, plan, settings, calibration, labels, options, None, progress)


def simulate_ompmc_on_mesh(density: Image, mesh: TetMesh, plan: Plan,
                           settings: TransportSettings, *,
                           calibration: HUCalibration | None = None,
                           labels: Image | None = None, options: OmpmcOptions | None = None,
                           progress: bool | None = None) -> tuple[DoseResult, DoseResult]:
    """(mesh result, voxel result) of :func:`simulate_ompmc` with a mesh: the voxel run and its
    energy put on the tets by :func:`tetdose.coupling.onto_mesh.result_onto_mesh`."""
    if calibration is not None:
        density = density.with_array(calibration.density_checked(density.array)[0].astype(np.float64))
    voxel = _simulate(density, plan, settings, None, labels, options, mesh, progress)
    return result_onto_mesh(voxel, density, mesh), voxel


def _simulate(density: Image, plan: Plan, settings: TransportSettings,
              calibration: HUCalibration | None, labels: Image | None,
              options: OmpmcOptions | None, mesh: TetMesh | None,
              progress: bool | None) -> DoseResult:
    """The voxel run (``mesh``: where the target region may be)."""
    om = ompmc_module()
    options = options or OmpmcOptions()
    if calibration is not None:
        density = density.with_array(calibration.density_checked(density.array)[0].astype(np.float64))
    plan.require_resolved()
    world = ompmc_world(density, plan, options, labels)
    pegs = pegs_path(options.pegs)
    ecut, pcut = _cutoffs(options, settings, world.media, pegs)
    threads = int(options.threads or numba.get_num_threads())
    threads_set = set_threads(om, threads)
    geometry = om.Geometry(*world.bounds_cm, world.media, world.density, world.material)
    target = _target_weights(density, labels, mesh, plan, settings)
    reached = None
    t0, cpu0 = time.perf_counter(), time.process_time()
    bounds = _batch_bounds(settings)
    per_batch = np.diff(bounds)
    energy = np.zeros((settings.n_batches, len(world.mass_g)))
    ledger = np.zeros((settings.n_batches, 5))
    counts = np.zeros((settings.n_batches, 7), dtype=np.int64)
    with tempfile.TemporaryDirectory(prefix="tetdose-ompmc-") as tmp:
        physics = {"pegs_file": str(pegs), "global_ecut": ecut, "global_pcut": pcut,
                   "n_split": int(options.n_split), "output_folder": tmp}
        eng = _Engine(om, geometry, density.grid, physics, Path(tmp))
        _preflight(eng, plan, settings)
        with tqdm(total=settings.n_batches, unit="batch", desc="ompmc transport",
                  disable=None if progress is None else not progress,
                  delay=PROGRESS_DELAY_S) as bar:
            for b in range(settings.n_batches):
                energy[b], ledger[b], counts[b] = _run_batch(
                    eng, plan, settings, b, int(bounds[b]), int(bounds[b + 1] - bounds[b]))
                bar.update(1)
                done = b + 1
                if target is not None and MIN_TARGET_BATCHES <= done < settings.n_batches:
                    achieved = _region_error(energy[:done] @ target, per_batch[:done])
                    bar.set_postfix_str(f"σ/D {100 * achieved:.2f} %")
                    if achieved <= settings.target_uncertainty:
                        reached = done
                        break
    record = {
        "engine": "ompmc", "ompmc_version": str(om.__version__),
        "physics": "dose (coupled photon-electron transport, EGSnrc physics by ompmc)",
        "pegs": pegs.name, "electron_cutoff_mev": ecut - ELECTRON_MASS_MEV,
        "ecut_total_mev": ecut, "photon_cutoff_mev": pcut, "n_split": int(options.n_split),
        "media": {n: c._asdict() for n, c in world.choices.items()},
        "source": "tetdose's source particles as an IAEA phase space, one per history",
        "threads": threads if threads_set else "OMP_NUM_THREADS",
        "materials": list(world.choices), "n_cells": len(world.mass_g),
        "unscored_voxels": unscored_voxels(density),
        "cpu_s": time.process_time() - cpu0}
    done = reached or settings.n_batches
    if target is not None:
        record["target"] = {"uncertainty": settings.target_uncertainty,
                            "region": resolved_target(settings, plan).target_region,
                            "reached": reached is not None,
                            "batches": done, "histories": int(per_batch[:done].sum()),
                            "achieved": _region_error(energy[:done] @ target, per_batch[:done])}
        warn_target_missed(record["target"])
    factor, conversion = water_factors(plan_media(list(world.choices), plan), settings)
    if conversion:  # D_w = D_m · s_w,m of each voxel's tetdose material
        energy *= factor[world.cell_material][None, :]
    record.update(dose_to=settings.dose_to, **conversion)
    result = DoseResult(energy[:done], per_batch[:done], world.mass_g, ledger[:done],
                        counts[:done], plan.particles, settings.seed, "analog", "voxel",
                        time.perf_counter() - t0, __version__, density.grid, record)
    return result


def unscored_voxels(density: Image) -> int:
    """Voxels of ``density`` [g/cm³] above 0 and below :data:`UNSCORED_BELOW_G_CM3`, where ompmc
    scores no energy (module docstring); warns when there are any."""
    rho = np.asarray(density.array)
    n = int(np.count_nonzero((rho > 0.0) & (rho < UNSCORED_BELOW_G_CM3)))
    if n:
        warnings.warn(f"{n} voxels are below {UNSCORED_BELOW_G_CM3} g/cm³, where ompmc scores no "
                      f"energy: their dose is 0 with --engine ompmc (airways, air around the "
                      f"patient); tetdose's own engine scores them", stacklevel=3)
    return n


def _target_weights(density: Image, labels: Image | None, mesh: TetMesh | None, plan: Plan,
                    settings: TransportSettings) -> FloatArray | None:
    """Voxel weights w_v whose energy Σ_v E_v w_v is the target region's (``target_uncertainty``,
    as tetdose's engine: ``target_region``, else the prescription's structure): the region's tets
    of ``mesh`` (w_v = Σ_{k ∈ region} Vol(v ∩ k) / V_v) when the mesh holds it, else its voxels
    in ``labels``. None without a target."""
    if settings.target_uncertainty is None:
        return None
    if settings.target_statistic != "mean":
        raise OptionError("the ompmc engine stops on the σ of the target's mean dose: drop "
                          "--target-statistic median (tetdose's engine has it)")
    if mesh is not None:
        with contextlib.suppress(PlanError):
            cells = target_cells(mesh, plan, settings)
            return np.asarray(voxel_share(mesh, density.grid)[np.flatnonzero(cells)]
                              .sum(axis=0)).ravel()
    cells = target_cells(World(density=density, labels=labels), plan, settings)
    return np.asarray(cells, dtype=np.float64)


def _region_error(energy: FloatArray, histories: IntArray) -> float:
    """Relative standard error of the mean of the batch estimates x_b = E_b / n_b (the batch
    statistics of :attr:`DoseResult.dose_std_gy`); ∞ while the region has no energy."""
    x = energy / histories
    mean = x.mean()
    if len(x) < 2 or mean <= 0.0:
        return float("inf")
    return float(np.sqrt(((x - mean) ** 2).sum() / (len(x) * (len(x) - 1))) / mean)


def _preflight(eng: _Engine, plan: Plan, settings: TransportSettings) -> None:
    """Refuse beams none of whose first :data:`PILOT_HISTORIES` particles meets the grid."""
    n = min(settings.n_histories, PILOT_HISTORIES)
    grid = eng.grid
    p = source_particles(plan, settings, 0, n,
                         lambda a, d: a @ grid.direction if d else grid.to_grid_frame(a))
    lo, hi = grid.bounds_grid_frame()
    if not np.any(ray_hits_box(p.position_mm, p.direction, lo, hi)):
        raise PlanError(f"none of the first {n} source photons reaches the CT grid: the beams "
                        "miss it; check the beams' position_mm / direction / isocentre against "
                        "the CT coordinates (mm, patient frame)")


def ray_hits_box(position: FloatArray, direction: FloatArray, lo: FloatArray, hi: FloatArray
                 ) -> np.ndarray:
    """Whether each ray p + t·d, t ≥ 0, passes through the box [lo, hi] (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - position) / direction
        t2 = (hi - position) / direction
    inside = (position >= lo) & (position <= hi)
    t_lo = np.where(direction == 0.0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(direction == 0.0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter = np.maximum(t_lo.max(axis=1), 0.0)
    return enter < t_hi.min(axis=1)


def phase_engine(options: OmpmcOptions | None = None, progress: bool | None = None
                 ) -> Callable[[Image, TetMesh, Plan, TransportSettings],
                               tuple[DoseResult, DoseResult]]:
    """ompmc as the voxel engine of :func:`tetdose.dose.dose4d.run_dose4d`: each phase's body
    CT [g/cm³] through :func:`simulate_ompmc`, its voxel energy put on the phase mesh by
    :func:`tetdose.coupling.onto_mesh.result_onto_mesh`; returns (mesh result, voxel result)."""
    def run(density: Image, mesh: TetMesh, plan: Plan, settings: TransportSettings
            ) -> tuple[DoseResult, DoseResult]:
        return simulate_ompmc_on_mesh(density, mesh, plan, settings, options=options,
                                      progress=progress)

    return run
