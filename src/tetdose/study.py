"""The end-to-end study run by ``tetdose demo`` (and ``make demo``) on a built-in phantom.

A real-patient-like study: only what moves — the lungs (with their vessels) and the tumour — is
meshed, as one conforming mesh; the rest of the body stays CT voxels. Every stage is the real
pipeline: map the CT onto the organ mesh (against the paper's Monte Carlo least squares as
baseline), deform through breathing phases with mass-conserving densities, write the virtual
4D-CT (DICOM and NRRD) and the ParaView series, transport photons through every phase's body
with the organ mesh inside it (the hybrid world) and on the same body's voxels alone, accumulate
on the mesh, on the body's voxels and by the two voxel methods, compare inside the mesh (gamma,
DVH, profiles), export RT Dose, and write ``report.html`` and ``summary.json``. The whole output
folder is written atomically: an interrupted run leaves the previous output untouched.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tetdose._atomic import atomic_write_dir
from tetdose._constants import MM3_PER_CM3
from tetdose._typing import FloatArray
from tetdose.compare.comparison import half_inside
from tetdose.compare.consistency import expected_gamma_pass, mesh_std_to_grid, pair_significance
from tetdose.compare.dose_kerma import beam_axis_profiles, dose_kerma_figure, structure_ratios
from tetdose.compare.dvh_bands import banded_dvh, compare_points
from tetdose.compare.gamma import gamma_index
from tetdose.compare.profiles import image_profile, mesh_profile
from tetdose.compare.report import (
    Figure,
    dose_slices_figure,
    dvh_figure,
    gamma_figure,
    profiles_figure,
    pyplot,
    render_png,
    write_report,
)
from tetdose.core.body import TISSUE_FLOOR_G_CM3
from tetdose.core.calibration import HUCalibration
from tetdose.core.image import Image
from tetdose.core.io import write_mesh
from tetdose.core.mesh import TetMesh
from tetdose.core.overlap import Overlap, compute_overlap
from tetdose.core.transfer import grid_dose_to_mesh, mesh_dose_to_grid
from tetdose.dicom import write_rt_dose
from tetdose.dose.buildup import build_up_fraction, build_up_mask
from tetdose.dose.dose4d import run_dose4d, write_dose4d
from tetdose.errors import MeshError
from tetdose.mapping import map_density
from tetdose.mapping.figures import plot_evaluation
from tetdose.mapping.metrics import evaluate
from tetdose.motion import BreathingModel, update_series
from tetdose.motion.ct4d import phase_densities, to_hu, write_4dct
from tetdose.phantoms import Phantom, make_phantom, write_phantom
from tetdose.phantoms import organ_mesh as phantoms_organ_mesh
from tetdose.plan.beams import ControlPoint, LinacBeam, beam_axes
from tetdose.plan.prescription import PER_PHOTON_UNIT, Prescription
from tetdose.plan.spectra import build_up_depth_mm
from tetdose.transport import Plan, TransportSettings, World, simulate
from tetdose.transport.run.job import physics_record

#: Structures reported in the DVH and mapping tables (phantom label names).
STRUCTURES = ("tumour", "lung", "liver", "vessels", "bone")
#: What moves with breathing and is meshed (phantom label names); the rest of the body is CT.
MOVING = ("lung", "vessels", "tumour")
#: Dose unit of the study's figures: the plan is prescribed (see :func:`_plan`).
_UNIT = "Gy per fraction"


@dataclass(frozen=True)
class StudyConfig:
    """What the study runs: phantom, breathing, beams and Monte Carlo sizes."""

    phantom: str = "thorax"
    size: str = "medium"
    seed: int = 1
    n_phases: int = 10
    amplitude_mm: float = 12.0
    histories: int = 40_000  # per phase and geometry (each split into photon_splitting copies)
    physics: str = "dose"  # absorbed dose (electrons transported), or "kerma"
    electron_cutoff_mev: float = 0.2
    #: XVMC's splitting along the ray (TransportSettings): 4.2× the analog efficiency in the
    #: tumour (12.8 % → 6.2 % median per-tet σ at the same dose time, 3·10⁵ analog photons);
    #: the source photon in 64 copies, every later photon of weight 1 in 32: the tumour's σ²
    #: ÷ 1.8 against 32 / 32 for 1.25× the dose time (6.1 → 4.5 % accumulated).
    photon_splitting: int = 64
    splitting_scheme: str = "repeat"
    #: Copies of every later photon of weight 1 (TransportSettings); None: photon_splitting.
    secondary_photon_splitting: int | None = 32
    #: Source photons from scrambled Sobol points (TransportSettings.quasi_random): with the
    #: splitting, the tumour's median per-tet σ² 1.06–1.08× lower (demo, same time).
    quasi_random: bool = True
    kerma_histories: int = 300_000  # the dose-vs-kerma comparison's (analog kerma)
    batches: int = 10
    beam_angles_deg: tuple[float, ...] = (0.0, 120.0, 240.0)
    field_mm: float = 60.0
    paper_samples: int = 500  # hit-and-miss points per tet for the paper's baseline
    #: Target edges [mm] of meshed structures by name (as ``tetdose mesh --size-mm``); a
    #: structure not named gets its default (:func:`tetdose.meshing.labels.default_sizes_mm`).
    #: The tumour's trade of resolution for per-tet precision is measured in
    #: bench/demo_precision.py.
    mesh_size_mm: tuple[tuple[str, float], ...] = ()

    @classmethod
    def quick(cls, **changes: Any) -> StudyConfig:
        """The `--quick` study: small phantom, fewer histories (under two minutes)."""
        return cls(**{"size": "small", "histories": 2_500, "kerma_histories": 20_000,
                      "paper_samples": 200, **changes})


def run_study(config: StudyConfig, out_dir: str | os.PathLike[str], *,
              log: Callable[[str], None] = lambda line: None, progress: bool = False
              ) -> dict[str, Any]:
    """Run the study into ``out_dir`` (replaced atomically); return the summary."""
    summary: dict[str, Any] = {"config": asdict(config), "seconds": {}}
    with atomic_write_dir(out_dir) as tmp:
        _Run(config, tmp, summary, log, progress).all()
        shutil.copy(tmp / "report" / "report.html", tmp / "report.html")
        shutil.copy(tmp / "report" / "summary.json", tmp / "summary.json")
    return summary


class _Run:
    """The stages of one study; each adds to the summary, the figures and the output folder."""

    def __init__(self, config: StudyConfig, out: Path, summary: dict[str, Any],
                 log: Callable[[str], None], progress: bool) -> None:
        self.c, self.out, self.summary, self.log, self.progress = config, out, summary, log, \
            progress
        self.figures: list[Figure] = []

    def all(self) -> None:
        for stage in (self.phantom, self.mapping, self.motion, self.ct4d, self.dose,
                      self.kerma, self.compare):
            start = time.perf_counter()
            line = stage()
            seconds = time.perf_counter() - start
            self.summary["seconds"][stage.__name__] = round(seconds, 2)
            self.log(f"[{stage.__name__:8s} {seconds:6.1f} s] {line}")
        write_report(self.out / "report", self.figures, self.summary,
                     title=f"tetdose study: {self.c.phantom} phantom, {self.c.n_phases} phases")

    def phantom(self) -> str:
        self.ph = make_phantom(self.c.phantom, seed=self.c.seed, size=self.c.size)
        write_phantom(self.ph, self.out / "phantom")
        self.label_of = {name: label for label, name in self.ph.label_names.items()}
        self.mesh = organ_mesh(self.ph, MOVING, dict(self.c.mesh_size_mm))
        write_mesh(self.out / "phantom" / "organ_mesh.vtu", self.mesh)
        m = self.mesh
        self.summary["phantom"] = {"meshed": list(MOVING), "tets": m.n_tets,
                                   "labels": {self.ph.label_names[int(r)]: int(r)
                                              for r in np.unique(m.region)},
                                   "points": m.n_points, "ct_size": list(self.ph.ct.grid.size),
                                   "spacing_mm": self.ph.ct.grid.spacing_mm.tolist()}
        return (f"{self.c.phantom}: {', '.join(MOVING)} meshed ({m.n_tets} tets), the rest CT "
                f"{self.ph.ct.grid.size}")

    def mapping(self) -> str:
        ct, mesh = self.ph.ct, self.mesh
        self.mapped = map_density(mesh, ct, progress=self.progress)
        runs = {"l2 exact (tetdose)": self.mapped,
                "lsq monte-carlo (paper)": map_density(mesh, ct, solver="lsq",
                                                       overlap="monte-carlo",
                                                       n_samples=self.c.paper_samples),
                "l2 exact, split by region": map_density(mesh, ct, by_region=True)}
        write_mesh(self.out / "mapping" / "mapped.vtu", self.mapped.mesh)
        cover = (self.mapped.overlap.covered_volume_per_voxel_mm3().reshape(ct.grid.shape)
                 / ct.grid.voxel_volume_mm3)
        table: dict[str, Any] = {}
        for method, dm in runs.items():
            # Reconstruct with exact volumes whatever the mapping used (the split mesh has its own).
            exact = dm.overlap if dm.overlap.method == "exact" else self.mapped.overlap
            row = {"mesh_mass_g": dm.mesh_mass_g, "ct_mass_in_mesh_g": dm.ct_mass_covered_g,
                   "mass_error_in_mesh_pct": 100 * dm.mass_error_covered}
            for name in ("all", *STRUCTURES):
                roi = cover >= 0.5
                if name != "all":
                    region = self.ph.labels.array == self.label_of.get(name, -1)
                    if (roi & region).sum() < 0.5 * region.sum():  # the mesh does not cover it
                        row.setdefault("not_meshed", []).append(name)
                        continue
                    roi &= region
                if roi.sum() < 10:
                    continue
                ev = evaluate(ct, dm.mesh, dm.density_g_cm3, roi=roi, overlap=exact)
                row[name] = {"rmde_pct": ev.metrics.rmde_pct, "esd_pct": ev.metrics.esd_pct,
                             "mass_error_pct": ev.metrics.mass_error_pct}
                if name == "all":
                    png = plot_evaluation(ev, self.out / "mapping" / f"{_slug(method)}.png",
                                          title=method)
                    self.figures.append(Figure(f"mapping_{_slug(method)}", f"Density mapping, "
                                               f"{method}: original, |error|, reconstruction "
                                               "(paper Fig. 13)", png.read_bytes()))
            table[method] = row
        self.summary["mapping"] = table
        ours, paper = table["l2 exact (tetdose)"], table["lsq monte-carlo (paper)"]
        return (f"RMDE {ours['all']['rmde_pct']:.2f} % (paper's method "
                f"{paper['all']['rmde_pct']:.2f} %), mass error in mesh "
                f"{ours['mass_error_in_mesh_pct']:.1e} % ({paper['mass_error_in_mesh_pct']:.2g} %)")

    def motion(self) -> str:
        model = BreathingModel(amplitude_mm=self.c.amplitude_mm)
        series = model.series(self.mapped.mesh, self.c.n_phases,
                              density_g_cm3=self.mapped.density_g_cm3)
        self.series, reports = update_series(series, self.mapped.density_g_cm3)
        self.series.write(self.out / "phases")
        self.summary["motion"] = [asdict(r) for r in reports]
        worst = max(abs(r.mass_change_rel) for r in reports)
        return f"{self.c.n_phases} phases, worst total-mass change {worst:.1e}"

    def ct4d(self) -> str:
        self.density = phase_densities(self.series, self.ph.ct, progress=self.progress)
        cal = HUCalibration.schneider2000()
        self.vct = [to_hu(rho, cal) for rho in self.density]
        pct = self.series.phase_percent
        write_4dct(self.vct, self.out / "ct4d" / "dicom", phase_percent=pct, fmt="dicom")
        write_4dct(self.vct, self.out / "ct4d" / "nrrd", phase_percent=pct, fmt="nrrd")
        self.figures.append(_phases_figure(self.vct, pct))
        return f"{len(self.vct)} phases as DICOM series and NRRD"

    def dose(self) -> str:
        tumour = self.mesh.centroids_mm[self.mesh.region == self.label_of["tumour"]]
        self.target_mm = tumour.mean(axis=0)
        plan = self.plan = _plan(self.target_mm, self.c, self.label_of["tumour"])
        settings = TransportSettings(n_histories=self.c.histories, n_batches=self.c.batches,
                                     seed=self.c.seed, physics=self.c.physics,
                                     electron_cutoff_mev=self.c.electron_cutoff_mev,
                                     photon_splitting=self.c.photon_splitting,
                                     splitting_scheme=self.c.splitting_scheme,
                                     secondary_photon_splitting=self.c.secondary_photon_splitting,
                                     quasi_random=self.c.quasi_random)
        self.d4 = run_dose4d(self.series, plan, settings, ct_hu=self.ph.ct,
                             phase_density=self.density, progress=self.progress)
        write_dose4d(self.d4, self.out / "dose4d")
        closure = max(r.ledger_closure for r in self.d4.results + self.d4.voxel.results)
        lost = sum(r.lost_photons for r in self.d4.results)
        self.summary["physics"] = physics_record(settings)
        self.summary["dose"] = {**self.d4.summary(), "ledger_closure_rel": closure,
                                "lost_photons": lost}
        rho_ct = HUCalibration.schneider2000().density(np.asarray(self.ph.ct.array))
        self.summary["precision"] = {
            name: tet_precision(self.d4, self.series.reference.region == label,
                                0.5 * plan.prescription.dose_gy,
                                voxel_mass_mg(rho_ct, self.ph.labels.array == label,
                                              self.ph.ct.grid.voxel_volume_mm3))
            for name, label in self.label_of.items()
            if name in MOVING and (self.series.reference.region == label).any()}
        n2 = self.c.secondary_photon_splitting
        split = (f" split {self.c.photon_splitting}×{f' (later photons {n2}×)' if n2 else ''} "
                 f"({self.c.splitting_scheme})" if self.c.photon_splitting > 1 else "")
        split += ", quasi-random" if self.c.quasi_random else ""
        return f"{self.c.physics}: {self.c.histories} histories{split} × {self.c.n_phases} " \
               f"phases × 2 worlds (organ mesh in the CT, CT alone); ledger closes to " \
               f"{closure:.1e}, {lost} lost photons"

    def kerma(self) -> str:
        """Where kerma ≠ dose, measured on phase 0 (:mod:`tetdose.compare.dose_kerma`): the same
        world, beams and streams without electrons; per structure D/K, per beam the axes."""
        if self.c.physics != "dose":
            return "skipped (the study's physics is kerma)"
        world = World(mesh=self.series.mesh(0), density=self.density[0])
        dose = self.d4.results[0]
        settings = TransportSettings(self.c.kerma_histories, self.c.batches, self.c.seed,
                                     physics="kerma")
        kerma = simulate(world, self.plan, settings, progress=False)
        kerma = replace(kerma, particles=dose.particles)  # the prescription's scale
        (d, sd), (k, sk) = dose.to_images(), kerma.to_images()
        masks = {name: self.ph.labels.array == label for name, label in self.label_of.items()
                 if name in STRUCTURES}
        ratios = structure_ratios(d, sd, k, sk, dose.combined().mass_g, masks)
        beams = [(b.name, self.target_mm, -beam_axes(g, 0.0, 0.0)[2])
                 for b, g in zip(self.plan.treatment_beams, self.c.beam_angles_deg, strict=True)]
        profiles = beam_axis_profiles(world, self.plan, replace(
            settings, n_histories=max(self.c.kerma_histories // 2, self.c.batches)), beams)
        self.figures.append(dose_kerma_figure(profiles, unit=PER_PHOTON_UNIT))
        self.summary["dose_vs_kerma"] = {
            "structures": ratios,
            "beams": {p.name: {f"dose_over_kerma_at_{z:g}_mm": p.ratio_at(z) for z in (2, 5, 10, 20)}
                      for p in profiles}}
        worst = min(ratios.items(), key=lambda kv: kv[1]["dose_over_kerma"])
        return (f"phase 0 kerma for comparison; lowest mean D/K {worst[1]['dose_over_kerma']:.3f} "
                f"({worst[0]}); D/K at 5 mm under the skin "
                f"{', '.join(f'{p.ratio_at(5.0):.2f}' for p in profiles)}")

    def compare(self) -> str:
        grid, d4 = self.ph.ct.grid, self.d4
        ref_mesh, phase0 = self.series.reference, self.series.mesh(0)
        ov0, ov_ref = compute_overlap(phase0, grid), self.mapped.overlap  # ref = mapped mesh
        static_mesh = mesh_dose_to_grid(phase0, d4.results[0].mesh_part().dose_gy, grid,
                                        overlap=ov0)
        static_vox = d4.voxel.doses[0]
        # The voxel dose seen at the mesh's resolution (energy-conserving there and back): what
        # differs from the mesh dose then is physics and statistics, not cell size.
        static_vox_on_mesh = mesh_dose_to_grid(
            phase0, grid_dose_to_mesh(phase0, static_vox, overlap=ov0), grid, overlap=ov0)
        acc_mesh = mesh_dose_to_grid(ref_mesh, d4.accumulated.dose_gy, grid, overlap=ov_ref)
        emt, ddm = d4.voxel.energy_mass_transfer, d4.voxel.direct_mapping
        # Gamma only where the mesh is: outside the body mesh only the voxel engine scores dose.
        inside = half_inside(ov0) & half_inside(ov_ref)
        # Global gamma normalised to the prescription (not to a noisy maximum voxel).
        rx = self.plan.prescription.dose_gy if self.plan.prescription else None
        k = int(grid.voxel_index(self.target_mm[None])[0, 2])
        pairs = {"static phase, matched resolution: voxel vs mesh": (static_vox_on_mesh,
                                                                     static_mesh),
                 "static phase: voxel vs mesh": (static_vox, static_mesh),
                 "accumulated: energy/mass transfer vs mesh": (emt, acc_mesh),
                 "accumulated: direct mapping vs mesh": (ddm, acc_mesh)}
        # The body stops at the skin: only tissue (density ≥ the floor) is compared.
        inside &= np.asarray(self.density[0].array) >= TISSUE_FLOOR_G_CM3
        sig = self._sigmas(ov0, ov_ref)
        gammas, significance = {}, {}
        masks = {n: self.ph.labels.array == self.label_of[n] for n in STRUCTURES
                 if n in self.label_of}
        weight = np.asarray(self.density[0].array) * grid.voxel_volume_mm3 / MM3_PER_CM3
        for name, (a, b) in pairs.items():
            kw = {"dose_percent": 3.0, "dta_mm": 3.0, "mask": inside, "normalization_gy": rx}
            g = gamma_index(a, b, **kw)
            row = g.summary()
            if name in sig:  # σ of both doses: the pass rate noise alone would give
                s_ref, s_ev = sig[name]
                row |= expected_gamma_pass(a, s_ref, b, s_ev, **kw)
                significance[name], figs = pair_significance(
                    a, s_ref, b, s_ev, inside, masks, 0.1 * (rx or g.normalization_gy), weight,
                    k=k if name.startswith("static phase:") else None,
                    labels=("mesh", name.split(": ")[1].split(" vs")[0]), unit=_UNIT)
                self.figures += figs
            gammas[f"{name} 3%/3mm global"] = row
            self.figures.append(gamma_figure(g, k=k, expected=row.get(
                "expected_pass_rate_percent")))
        self.summary["significance"] = significance
        self.summary["compared_region"] = (
            "voxels at least half inside the organ mesh in phase 0 and the reference phase, in "
            f"tissue (density ≥ {TISSUE_FLOOR_G_CM3:g} g/cm³ in phase 0)")
        named = {n: self.label_of[n] for n in STRUCTURES
                 if n in self.label_of and (ref_mesh.region == self.label_of[n]).any()}
        self.figures.append(dose_slices_figure(
            d4.body.combined, emt, labels=("organ mesh + body accumulated", "voxel EMT"), k=k,
            unit=_UNIT, ct_hu=self.ph.ct, mesh=ref_mesh, structures=named,
            prescription_gy=self.plan.prescription.dose_gy if self.plan.prescription else None,
            region=np.asarray(self.density[0].array) >= TISSUE_FLOOR_G_CM3))
        g = gamma_index(emt, d4.body.combined, dose_percent=3.0, dta_mm=3.0, normalization_gy=rx)
        gammas["accumulated, whole body: energy/mass transfer vs organ mesh + body 3%/3mm "
               "global"] = g.summary()
        self.summary["gamma"] = gammas
        self.summary["dvh"] = self._dvh(ref_mesh, emt, ddm, sig)
        self._profiles(ref_mesh, emt, ddm)
        write_rt_dose(d4.body.combined, self.out / "rtdose.dcm",
                      reference_ct=self.out / "ct4d" / "dicom" / "phase_000", plan=self.plan,
                      unit=_UNIT)
        matched = gammas["static phase, matched resolution: voxel vs mesh 3%/3mm global"]
        return (f"gamma 3%/3mm static phase {matched['pass_rate_percent']:.1f} % (matched "
                "resolution); RT Dose written")

    def _sigmas(self, ov0: Overlap, ov_ref: Overlap) -> dict[str, tuple[FloatArray, FloatArray]]:
        """(σ of the reference, σ of the evaluated dose) [Gy] on the CT grid for the pairs that
        have both: the static phase's mesh and voxel runs (batches), the accumulated mesh dose
        (phases' σ in quadrature) and the two voxel accumulations (:mod:`tetdose.dose.dose4d`)."""
        d4, grid = self.d4, self.ph.ct.grid
        mesh0 = mesh_std_to_grid(self.series.mesh(0), d4.results[0].mesh_part().dose_std_gy,
                                 grid, ov0).array
        acc = d4.accumulated
        acc_std = (np.zeros(grid.shape) if acc.dose_std_gy is None else
                   mesh_std_to_grid(self.series.reference, acc.dose_std_gy, grid, ov_ref).array)
        v = d4.voxel
        return {"static phase: voxel vs mesh": (v.results[0].to_images()[1].array, mesh0),
                "accumulated: energy/mass transfer vs mesh": (v.energy_mass_transfer_std.array,
                                                              acc_std),
                "accumulated: direct mapping vs mesh": (v.direct_mapping_std.array, acc_std)}

    def _dvh(self, ref_mesh, emt: Image, ddm: Image, sig: dict) -> dict[str, Any]:  # noqa: ANN001
        """DVHs of the accumulated doses with their ±1σ bands; per structure each DVH point,
        its σ, and the mesh–voxel differences flagged that exceed their combined σ."""
        curves, table = {}, {}
        acc, v_cm3 = self.d4.accumulated, self.ph.ct.grid.voxel_volume_mm3 / MM3_PER_CM3
        s_emt = sig["accumulated: energy/mass transfer vs mesh"][0]
        s_ddm = sig["accumulated: direct mapping vs mesh"][0]
        for name in STRUCTURES:
            label = self.label_of.get(name)
            mask = self.ph.labels.array == label
            sel = ref_mesh.region == label
            if label is None or not sel.any() or mask.sum() < 5:
                continue
            hs = [banded_dvh(acc.dose_gy[sel], None if acc.dose_std_gy is None
                             else acc.dose_std_gy[sel], ref_mesh.volumes_mm3[sel] / MM3_PER_CM3,
                             name="mesh"),
                  *(banded_dvh(img.array[mask], s[mask], np.full(int(mask.sum()), v_cm3),
                               name=n) for img, s, n in ((emt, s_emt, "voxel EMT"),
                                                         (ddm, s_ddm, "voxel DDM")))]
            curves[name] = hs
            table[name] = {h.name: h.metrics() | {"sigma": h.metrics_sigma()} for h in hs}
            table[name]["points"] = {f"mesh − {h.name}": compare_points(hs[0], h)
                                     for h in hs[1:]}
        if self.c.physics == "dose":  # measured on phase 0 (stage kerma): dose < 95 % of kerma
            below = {n: r["mass_fraction_dose_below_kerma"]
                     for n, r in self.summary["dose_vs_kerma"]["structures"].items()}
            self.figures.append(dvh_figure(curves, unit=_UNIT, below_kerma_fraction=below))
        else:
            ct = self.ph.ct
            build_up = build_up_mask(ct.with_array(HUCalibration.schneider2000().density(
                ct.array)), build_up_depth_mm("6MV"))
            in_build_up = {n: build_up_fraction(build_up, self.ph.labels.array ==
                                                self.label_of[n]) for n in curves}
            self.summary["build_up_fraction"] = in_build_up
            self.figures.append(dvh_figure(curves, unit=_UNIT, build_up_mm=build_up_depth_mm(
                "6MV"), build_up_fraction=in_build_up))
        return table

    def _profiles(self, ref_mesh, emt: Image, ddm: Image) -> None:  # noqa: ANN001
        t = self.target_mm
        a, b = t - [120.0, 0, 0], t + [120.0, 0, 0]
        self.figures.append(profiles_figure(
            [mesh_profile(ref_mesh, self.d4.accumulated.dose_gy, a, b, label="mesh"),
             image_profile(emt, a, b, label="voxel EMT"),
             image_profile(ddm, a, b, label="voxel DDM")], name="profile_lr_through_tumour",
            unit=_UNIT))


def _plan(target_mm: np.ndarray, c: StudyConfig, tumour_label: int) -> Plan:
    """6 MV linac fields (IEC gantry angles, HFS) at the tumour centroid, square jaws of
    ``field_mm`` at the isocentre, prescribed 2 Gy per fraction to the tumour's mean dose (30
    fractions): every dose of the study is then in Gy per fraction (tetdose.plan.prescription).
    The mean, not D95: with electrons each small tet's dose carries ~10–20 % noise at the demo's
    histories, which biases a D95 low (and the prescribed dose high, ~1.5× in the mean); the mean
    is unbiased."""
    half = c.field_mm / 2.0
    beams = tuple(LinacBeam(f"G{g:g}", "6MV", target_mm,
                            (ControlPoint(g, 0.0, 0.0, (-half, half, -half, half)),))
                  for g in c.beam_angles_deg)
    return Plan(treatment_beams=beams, regions={"tumour": tumour_label},
                prescription=Prescription("tumour", 2.0, "mean", 30))


def _phases_figure(images: list[Image], percent: np.ndarray) -> Figure:
    """Coronal slices of the virtual 4D-CT at a few phases."""
    plt = pyplot()
    picks = sorted({0, len(images) // 4, len(images) // 2, len(images) - 1})
    fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 3.6))
    j = images[0].grid.shape[1] // 2
    sx, _, sz = images[0].grid.spacing_mm
    for ax, p in zip(np.atleast_1d(axes), picks, strict=True):
        ax.imshow(images[p].array[:, j, :], cmap="gray", vmin=-1000, vmax=400, origin="lower",
                  aspect=sz / sx)
        ax.set_title(f"phase {percent[p]:.0f} %")
        ax.set_axis_off()
    return Figure("ct4d_phases", "Virtual 4D-CT, coronal slices (HU −1000…400)", render_png(fig))


def voxel_mass_mg(density_g_cm3: np.ndarray, mask: np.ndarray, voxel_mm3: float) -> float:
    """Median mass [mg] of the CT voxels in ``mask``: ρ [g/cm³] = [mg/mm³] × voxel volume."""
    return float(np.median(np.asarray(density_g_cm3)[mask])) * voxel_mm3


def tet_precision(d4: Any, tets: np.ndarray, floor_gy: float, voxel_mg: float) -> dict[str, Any]:
    """Per-tet precision of a structure's tets (boolean ``tets`` on the reference mesh): their
    count and median time-weighted mass [mg] beside its CT voxels' median mass ``voxel_mg``; the
    median relative σ [%] of the accumulated dose and of each phase's dose over those of its tets
    whose accumulated dose reaches ``floor_gy`` (a tet without dose counts as σ = ∞)."""
    acc = d4.accumulated
    sel = tets & (acc.dose_gy >= floor_gy)

    def median_pct(dose: FloatArray, std: FloatArray | None) -> float | None:
        if std is None or not sel.any():
            return None
        d, s = dose[sel], std[sel]
        rel = np.divide(s, d, out=np.full(len(d), np.inf), where=d > 0)
        return float(100.0 * np.median(rel))

    parts = [r.mesh_part() for r in d4.results]
    phases = [median_pct(p.dose_gy, p.dose_std_gy) for p in parts]
    return {"tets": int(tets.sum()), "median_tet_mass_mg": 1e3 * float(np.median(
                acc.mass_g[tets])), "ct_voxel_mass_mg": voxel_mg,
            "tets_scored": int(sel.sum()), "scored": f"accumulated dose ≥ {floor_gy:g} Gy",
            "median_sigma_pct": {
                "accumulated": median_pct(acc.dose_gy, acc.dose_std_gy),
                "phase_median": None if None in phases else float(np.median(phases)),
                "phases": phases}}


def organ_mesh(ph: Phantom, names: tuple[str, ...],
               size_mm: Mapping[str, float] | None = None) -> TetMesh:
    """One conforming, organ-shaped mesh (MMG level sets, :mod:`tetdose.meshing`) of the
    phantom's labels ``names``; vessels are folded into the lung that holds them (thinner than
    two voxels in places), so the regions are lung and tumour. ``size_mm``: target edge [mm] by
    region name (others: their default)."""
    label_of = {name: label for label, name in ph.label_names.items()}
    regions = {label_of[n]: (label_of[n],) for n in names if n in label_of and n != "vessels"}
    if "lung" in label_of and "vessels" in label_of and "vessels" in names:
        regions[label_of["lung"]] = (label_of["lung"], label_of["vessels"])
    sizes = dict(size_mm or {})
    meshed = sorted(ph.label_names[r] for r in regions)
    if unknown := sorted(set(sizes) - set(meshed)):
        raise MeshError(f"no meshed structure named {', '.join(unknown)} for a target size; "
                        f"the meshed ones are {', '.join(meshed)}")
    return phantoms_organ_mesh(ph, regions,
                               {label_of[n]: float(h) for n, h in sizes.items()} or None)


def _slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in text).strip("_").lower()
