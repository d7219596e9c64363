"""The plan: photon sources (beams), region materials, normalization, prescription or MU
calibration. Frozen dataclasses validated on construction (errors are :class:`PlanError`).

``plan.toml`` (parsed with :mod:`tomllib`)::

    [[beam]]
    type = "point"              # "pencil" | "parallel" | "point" | "linac" (see below) | "volume"
                                # (tetdose.plan.volume_source)
    particle = "photon"         # "photon" | "electron" | "positron" (e±: physics "dose")
    energy_mev = 1.0            # or spectrum = "6MV" | "10MV" | "15MV" | "Co60" | "Co60scatter"
                                # (named, see transport.spectra) | "spectrum.csv" (columns
                                # energy_mev, weight; also for linac beams)
    position_mm = [0.0, 0.0, 0.0]
    direction = [0.0, 0.0, 1.0] # pencil / parallel axis, cone axis
    field_mm = [100.0, 100.0]   # parallel: field size (x along e1, y along e2)
    half_angle_deg = 180.0      # point: 180 = isotropic
    weight = 1.0                # relative weight between beams
    [materials]
    1 = "water"                 # region label → material name (built-in, or defined below)
    2 = "my_bone"
    [materials.my_bone]         # a composition by name (tetdose.core.composition)
    composition = { H = 0.047234, C = 0.14433, N = 0.04199, O = 0.446096, Mg = 0.0022,
                    P = 0.10497, S = 0.00315, Ca = 0.20993, Zn = 0.0001 }  # mass fractions
    density = 1.85              # nominal density [g/cm³] (its density effect; recorded)
    mean_excitation_ev = 106.4  # optional (default: ICRU 37's Bragg rule)
    [normalization]
    particles = 1.0             # dose reported for this many source particles

    [[beam]]                    # a treatment beam (IEC 61217, see transport.beams)
    type = "linac"
    name = "AP"
    spectrum = "6MV"
    isocenter_mm = [0.0, 0.0, 0.0]   # or isocenter = "tumour" ([regions] name or a label)
    gantry_deg = 0.0
    collimator_deg = 0.0
    couch_deg = 0.0
    sad_mm = 1000.0
    jaws_mm = [-50.0, 50.0, -50.0, 50.0]    # x1, x2, y1, y2 at the isocentre plane
    mlc = { boundaries_mm = [...], positions_mm = [...], axis = "X" }  # optional MLCX/MLCY
    weight = 1.0                # meterset (MU) of the beam
    fluence_mode = "STANDARD"   # or "FFF" (computed with the same spectrum, flat fluence)
    # A delivery (tetdose.plan.beams): control points, each changing what it names, with the
    # cumulative meterset weight and the rotation directions towards the next one:
    # control_points = [{ meterset_weight = 0, gantry_deg = 0, gantry_direction = "CW",
    #                     mlc = [...2N leaf positions...], jaws_mm = [...] },
    #                   { meterset_weight = 1, gantry_deg = 180 }]
    # or an arc at the beam's aperture (start = stop: a full turn):
    # arc = { start_deg = 181.0, stop_deg = 179.0, direction = "CW" }
    [patient]
    position = "HFS"            # "HFS" | "HFP" | "FFS" | "FFP"
    [regions]
    tumour = 1                  # structure name → region label
    [prescription]              # scales every dose to Gy (tetdose.plan.prescription)
    structure = "tumour"
    dose_gy = 2.0               # per fraction
    metric = "D95"              # "D95" | "D50" | "mean"
    fractions = 30
    [calibration]               # or: absolute dose from the MU (tetdose.plan.mu_calibration)
    gy_per_mu = 0.00667         # Gy per MU at 100 mm depth, SSD 1000 mm, 100 × 100 mm²
    # rtplan = "plan.dcm"       # beams of a DICOM RT Plan (tetdose.plan.rt_plan), added
    # fraction_group = 1        # its fraction group (FractionGroupNumber; needed if several)

Field axes: ``e1`` is the unit vector of ``field_x_direction`` (default: the patient axis least
aligned with the beam) made orthogonal to the beam axis; ``e2 = axis × e1``.
"""

from __future__ import annotations

import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tetdose.core.composition import Material, material_from_table
from tetdose.errors import PlanError
from tetdose.plan.beams import LinacBeam
from tetdose.plan.photon_source import PhotonSource, check_source_keys
from tetdose.plan.segments import DynamicSegment, beam_sources
from tetdose.plan.spectra import is_named, named_spectrum, read_spectrum
from tetdose.plan.volume_source import VolumeSource, volume_source_from_dict

if TYPE_CHECKING:
    from tetdose.plan.mu_calibration import MUCalibration
    from tetdose.plan.prescription import Prescription

_SECTIONS = {"beam", "materials", "normalization", "regions", "prescription", "patient",
             "rtplan", "calibration", "fraction_group"}
_BEAM_KEYS = {"type", "particle", "energy_mev", "spectrum", "position_mm", "direction", "field_mm",
              "half_angle_deg", "weight", "field_x_direction"}


@dataclass(frozen=True, eq=False)
class Plan:
    """Beams, treatment (linac) beams, region names and materials, normalization, prescription.

    ``beams``: simple sources (pencil, parallel, point); ``treatment_beams``: :class:`LinacBeam`
    (from ``type = "linac"`` tables or an RT Plan); :attr:`sources` is both, flattened (one
    source per control-point interval that delivers meterset: a static point source, or a
    :class:`~tetdose.plan.segments.DynamicSegment` while the machine moves). ``regions``:
    structure name → region label (``[regions]``). ``volume_sources``: :class:`VolumeSource`
    (``type = "volume"``), particles born inside the world. ``compositions``: material name →
    :class:`~tetdose.core.composition.Material` of the ``[materials.NAME]`` tables (a table
    given inside ``materials`` is moved here), usable as a built-in name.
    """

    beams: tuple[PhotonSource, ...] = ()
    materials: Mapping[int, str] = field(default_factory=dict)
    particles: float = 1.0
    treatment_beams: tuple[LinacBeam, ...] = ()
    regions: Mapping[str, int] = field(default_factory=dict)
    prescription: Prescription | None = None
    calibration: MUCalibration | None = None
    volume_sources: tuple[VolumeSource, ...] = ()
    compositions: Mapping[str, Material] = field(default_factory=dict)
    sources: tuple[PhotonSource | DynamicSegment, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        beams, linacs = tuple(self.beams), tuple(self.treatment_beams)
        volumes = tuple(self.volume_sources)
        if not all(isinstance(b, PhotonSource) for b in beams) or not all(
                isinstance(b, LinacBeam) for b in linacs) or not all(
                isinstance(v, VolumeSource) for v in volumes):
            raise PlanError("plan beams must be PhotonSource, treatment_beams LinacBeam and "
                            "volume_sources VolumeSource")
        object.__setattr__(self, "volume_sources", volumes)
        if not beams and not linacs and not volumes:
            raise PlanError("a plan needs at least one beam ([[beam]] table in plan.toml, "
                            "or rtplan = \"plan.dcm\")")
        if self.prescription is not None and self.calibration is not None:
            raise PlanError("give either [prescription] (scale to a dose in a structure) or "
                            "[calibration] gy_per_mu (absolute dose from the MU), not both")
        if not (math.isfinite(self.particles) and self.particles > 0):
            raise PlanError(f"normalization particles must be positive, got {self.particles}")
        mats: dict[int, str] = {}
        comps = _compositions(self.materials, self.compositions)
        for key, name in dict(self.materials).items():
            if isinstance(name, Mapping):
                continue
            try:
                mats[int(key)] = str(name)
            except (TypeError, ValueError):
                raise PlanError(f"[materials] keys must be integer region labels, got {key!r}"
                                ) from None
        try:
            regions = {str(k): int(v) for k, v in dict(self.regions).items()}
        except (TypeError, ValueError):
            raise PlanError("[regions] maps structure names to integer labels, e.g. tumour = 3"
                            ) from None
        flat = list(beams)
        for lb in linacs:
            if lb.isocenter_region is None:
                flat.extend(beam_sources(lb))
        for k, v in (("beams", beams), ("treatment_beams", linacs), ("materials", mats),
                     ("regions", regions), ("sources", tuple(flat)), ("compositions", comps)):
            object.__setattr__(self, k, v)

    @property
    def unresolved(self) -> list[str]:
        """Structures named as isocentres and not yet located (see :meth:`resolved`)."""
        return [str(b.isocenter_region) for b in self.treatment_beams
                if b.isocenter_region is not None]

    def require_resolved(self) -> None:
        if self.unresolved:
            raise PlanError(f"isocenter = {self.unresolved[0]!r} needs the geometry: resolve it "
                            "with plan.resolved(geometry, labels) (tetdose dose does)")

    def resolved(self, geometry: Any, labels: Any = None) -> Plan:  # noqa: ANN401
        """This plan with every ``isocenter = "name"`` replaced by that region's centroid [mm]
        in ``geometry`` (TetMesh regions, or a label image beside a density image)."""
        from dataclasses import replace

        from tetdose.plan.prescription import region_centroid_mm, region_label

        if not self.unresolved:
            return self
        linacs = tuple(
            b if b.isocenter_region is None else replace(
                b, isocenter_mm=region_centroid_mm(
                    geometry, labels, region_label(b.isocenter_region, self.regions)),
                isocenter_region=None)
            for b in self.treatment_beams)
        return replace(self, treatment_beams=linacs)

    def rt_plan_dataset(self, ctx: Any, plan_uid: str, number: int) -> Any:  # noqa: ANN401
        """This plan's linac beams as a DICOM RT Plan dataset (:func:`tetdose.plan.rt_plan.plan_dataset`);
        what :func:`tetdose.dicom.write_rt_dose` writes beside a dose."""
        from tetdose.plan.rt_plan import plan_dataset

        return plan_dataset(self, ctx, plan_uid, number)

    @classmethod
    def from_rt_plan(cls, path: str | os.PathLike[str], fraction_group: int | None = None
                     ) -> Plan:
        """The photon beams of a DICOM RT Plan (:mod:`tetdose.plan.rt_plan_read`) as a plan:
        those of fraction group ``fraction_group`` (None: the plan's only one)."""
        from tetdose.plan.rt_plan_read import read_rt_plan_beams

        return cls(treatment_beams=read_rt_plan_beams(path, fraction_group))

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str],
                  rtplan: str | os.PathLike[str] | None = None,
                  fraction_group: int | None = None) -> Plan:
        """Read ``plan.toml`` (see module doc); spectrum paths are relative to the plan file.
        ``rtplan``: a DICOM RT Plan whose beams join the file's (``tetdose dose --rtplan``);
        ``fraction_group``: its fraction group (``--fraction-group``, else the file's
        ``fraction_group``, else the RT Plan's only one)."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except OSError as exc:
            raise PlanError(f"cannot read plan {path}: {exc.strerror}") from exc
        except tomllib.TOMLDecodeError as exc:
            raise PlanError(f"{path} is not valid TOML: {exc}") from exc
        return cls.from_dict(data, base_dir=path.parent, rtplan=rtplan,
                             fraction_group=fraction_group)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base_dir: Path = Path("."),
                  rtplan: str | os.PathLike[str] | None = None,
                  fraction_group: int | None = None) -> Plan:
        from tetdose.plan.beams import linac_beam_from_dict
        from tetdose.plan.mu_calibration import MUCalibration
        from tetdose.plan.prescription import Prescription

        unknown = set(data) - _SECTIONS
        if unknown:
            raise PlanError(f"unknown plan section(s) {sorted(unknown)}; use "
                            f"{', '.join(sorted(_SECTIONS))}")
        beams = data.get("beam", [])
        if not isinstance(beams, list):
            raise PlanError("beams must be given as [[beam]] tables")
        position = str(data.get("patient", {}).get("position", "HFS"))
        simple = tuple(_beam_from_dict(b, i, base_dir) for i, b in enumerate(beams)
                       if b.get("type") not in ("linac", "volume"))
        volumes = tuple(volume_source_from_dict(b, i, base_dir) for i, b in enumerate(beams)
                        if b.get("type") == "volume")
        linacs = [linac_beam_from_dict(b, i, position, base_dir) for i, b in enumerate(beams)
                  if b.get("type") == "linac"]
        dicom_plans = ([base_dir / str(data["rtplan"])] if "rtplan" in data else []) + (
            [Path(rtplan)] if rtplan is not None else [])
        if fraction_group is None and "fraction_group" in data:
            if not dicom_plans or isinstance(data["fraction_group"], bool) or not isinstance(
                    data["fraction_group"], int):
                raise PlanError("fraction_group = N (an integer) selects the fraction group of "
                                "the rtplan = \"plan.dcm\" beside it")
            fraction_group = data["fraction_group"]
        if fraction_group is not None and not dicom_plans:
            raise PlanError(f"fraction group {fraction_group} of which RT Plan? give --rtplan "
                            "plan.dcm (or rtplan = \"plan.dcm\" in plan.toml)")
        for dcm in dicom_plans:
            linacs.extend(cls.from_rt_plan(dcm, fraction_group).treatment_beams)
        norm = data.get("normalization", {})
        rx, cal = data.get("prescription"), data.get("calibration")
        return cls(simple, data.get("materials", {}), float(norm.get("particles", 1.0)),
                   tuple(linacs), data.get("regions", {}),
                   Prescription.from_dict(rx) if rx is not None else None,
                   MUCalibration.from_dict(cal) if cal is not None else None,
                   volume_sources=volumes)


def _compositions(materials: Mapping[Any, Any], given: Mapping[str, Material]
                  ) -> dict[str, Material]:
    """The ``[materials.NAME]`` tables among ``materials`` as Materials, with ``given``."""
    out = dict(given)
    if not all(isinstance(m, Material) for m in out.values()):
        raise PlanError("plan compositions must be Material values (tetdose.core.composition)")
    for name, table in dict(materials).items():
        if isinstance(table, Mapping):
            if str(name).lstrip("-").isdigit():
                raise PlanError(f"[materials] {name} = {{…}}: a region label takes a material "
                                "name; define the composition as [materials.NAME] and give "
                                f"{name} = \"NAME\"")
            out[str(name)] = material_from_table(str(name), table, f"[materials.{name}]")
    return out


def _beam_from_dict(d: Mapping[str, Any], i: int, base_dir: Path) -> PhotonSource:
    where = f"beam {i + 1}"
    check_source_keys(d, _BEAM_KEYS, where)
    if "type" not in d or "position_mm" not in d:
        raise PlanError(f"{where}: type and position_mm are required")
    _check_numbers(d, where)
    if "spectrum" in d and is_named(str(d["spectrum"])):
        energies, weights = named_spectrum(str(d["spectrum"]))
    elif "spectrum" in d:
        energies, weights = read_spectrum(base_dir / d["spectrum"])
    else:
        energies, weights = np.array([float(d["energy_mev"])]), np.ones(1)
    try:
        return PhotonSource(
            kind=d["type"], position_mm=d["position_mm"], direction=d.get("direction", (0, 0, 1)),
            energies_mev=energies, line_weights=weights, field_mm=d.get("field_mm", (0.0, 0.0)),
            half_angle_deg=float(d.get("half_angle_deg", 180.0)),
            weight=float(d.get("weight", 1.0)), field_x_direction=d.get("field_x_direction"),
            particle=str(d.get("particle", "photon")))
    except PlanError as exc:
        raise PlanError(f"{where}: {exc}") from None


#: plan.toml beam keys holding a number, and those holding a list of numbers (with an example).
_NUMBER_KEYS = ("energy_mev", "half_angle_deg", "weight")
_VECTOR_KEYS = {"position_mm": "[0.0, 0.0, -100.0]", "direction": "[0.0, 0.0, 1.0]",
                "field_mm": "[100.0, 100.0]", "field_x_direction": "[1.0, 0.0, 0.0]"}


def _check_numbers(d: Mapping[str, Any], where: str) -> None:
    """PlanError naming the key whose value is not a (finite) number or list of numbers."""
    for key in (*_NUMBER_KEYS, *_VECTOR_KEYS):
        if key not in d or (key == "field_x_direction" and d[key] is None):
            continue
        value = d[key]
        vector = key in _VECTOR_KEYS
        ok = isinstance(value, list) == vector and all(
            isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v)
            for v in (value if vector else [value]))
        if not ok:
            kind, example = ("a list of numbers", _VECTOR_KEYS[key]) if vector else \
                ("a number", "1.0")
            raise PlanError(f"{where}: {key} = {value!r} is not {kind}; write e.g. "
                            f"{key} = {example}")
