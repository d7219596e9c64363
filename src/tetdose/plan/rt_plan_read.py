"""Read the photon delivery of a DICOM RT Plan (PS3.3 A.20): every control point of every beam.

What is read, per treatment beam of the chosen fraction group (C.8.8.13: its BeamMeterset; a
plan with several fraction groups needs ``fraction_group``, since computing one of them silently
would be a wrong total):

- BeamType STATIC / DYNAMIC, SourceAxisDistance, the patient position of its setup
  (PatientSetupSequence), RadiationType PHOTON only;
- the energy: NominalBeamEnergy → named spectrum (≤ 1.5 MV: "Co60", else "<E>MV", one of the
  shipped spectra of :mod:`tetdose.plan.spectra`) and the fluence mode
  (PrimaryFluenceModeSequence): STANDARD, or NON_STANDARD "FFF" (flattening filter free), which
  is computed with the *flattened* spectrum of the same nominal energy and a flat fluence, and
  says so in a warning (no FFF spectrum or profile is shipped);
- per control point (C.8.8.14.5, attributes carried forward when a control point omits them):
  CumulativeMetersetWeight, GantryAngle, BeamLimitingDeviceAngle, PatientSupportAngle and their
  rotation directions (towards the next control point, C.8.8.14.8), IsocenterPosition, jaws
  X/ASYMX and Y/ASYMY (absent: ±200 mm), leaves MLCX or MLCY with the device's
  LeafPositionBoundaries. A STATIC beam does not move while the beam is on: its rotation
  directions are ignored. An angle a later control point omits is unchanged (C.8.8.14.5: an
  attribute that changes anywhere in the beam is given at every control point), so the segment
  towards it does not turn, whatever direction is carried forward; equal angles *stated* with
  CW/CC are a full turn (C.8.8.14.8 example 2) and a warning says so, as it does for direction
  NONE with a changing angle (read as the shorter turn).

Refused with a one-line :class:`PlanError` naming the beam and what it has: ion and brachy
plans, non-photon beams, wedges, compensators, blocks, boli, applicators, two MLCs (MLCX and
MLCY) or another device type, table-top pitch, roll or eccentric rotation, a change of energy
within a beam. Malformed plans too: no or empty ControlPointSequence, a control point without
CumulativeMetersetWeight, MLC without LeafPositionBoundaries or with the wrong number of leaf
positions, a first control point without GantryAngle, IsocenterPosition or NominalBeamEnergy,
BeamMeterset missing, 0 or negative, SourceAxisDistance below 500 mm.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any

import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError

from tetdose.errors import PlanError
from tetdose.plan.beams import MIN_SAD_MM, MLC, ControlPoint, LinacBeam, same_state

#: Jaw positions of an absent jaw pair [mm] (beyond any MLC field).
OPEN_JAW_MM = 200.0
#: Beam limiting device types read; every other one (e.g. MLCX1/MLCX2 stacked MLCs) is refused.
DEVICE_TYPES = ("X", "Y", "ASYMX", "ASYMY", "MLCX", "MLCY")
#: TreatmentDeliveryType of beams that deliver no dose and are skipped.
SKIPPED_DELIVERY = ("SETUP", "VERIFICATION")


def read_rt_plan_beams(path: str | os.PathLike[str], fraction_group: int | None = None
                       ) -> tuple[LinacBeam, ...]:
    """The photon treatment beams of fraction group ``fraction_group`` (FractionGroupNumber;
    None: the plan's only one) of an RT Plan, with every control point (see module doc)."""
    try:
        ds = pydicom.dcmread(path)
    except (OSError, InvalidDicomError) as exc:
        raise PlanError(f"cannot read RT Plan {path}: {exc}") from None
    if "IonBeamSequence" in ds:
        raise PlanError(f"{path} is an RT Ion Plan: ion beams are not modelled (photons only)")
    if "ApplicationSetupSequence" in ds or "BrachyTreatmentType" in ds:
        raise PlanError(f"{path} is a brachytherapy plan: only external photon beams are "
                        "modelled")
    if getattr(ds, "Modality", "") != "RTPLAN" or "BeamSequence" not in ds:
        raise PlanError(f"{path} is not an RT Plan with a BeamSequence")
    metersets = _fraction_group_metersets(ds, path, fraction_group)
    setups = {int(s.PatientSetupNumber): str(s.get("PatientPosition", "") or "")
              for s in ds.get("PatientSetupSequence", [])}
    by_number = {int(b.BeamNumber): b for b in ds.BeamSequence}
    missing = sorted(set(metersets) - set(by_number))
    if missing:
        raise PlanError(f"{path}: the fraction group references beam number(s) {missing}, "
                        "which the BeamSequence lacks")
    beams = []
    for number, beam in by_number.items():
        if number not in metersets or beam.get("TreatmentDeliveryType") in SKIPPED_DELIVERY:
            continue
        beams.append(_read_beam(beam, setups, metersets[number]))
    if not beams:
        raise PlanError(f"{path}: no treatment beam in the fraction group")
    return tuple(beams)


def _fraction_group_metersets(ds: Dataset, path: Any, number: int | None  # noqa: ANN401
                              ) -> dict[int, Any]:
    """BeamMeterset (None where absent) by beam number of the chosen fraction group."""
    groups = list(ds.get("FractionGroupSequence", []))
    if not groups:
        raise PlanError(f"{path} has no FractionGroupSequence: the beams' BeamMeterset (MU) "
                        "is unknown")

    def describe(g: Dataset) -> str:
        refs = [int(r.ReferencedBeamNumber) for r in g.get("ReferencedBeamSequence", [])]
        return (f"{int(g.FractionGroupNumber)}: {g.get('NumberOfFractionsPlanned', '?')} "
                f"fractions, beams {refs}")

    if number is None and len(groups) > 1:
        raise PlanError(f"{path} has {len(groups)} fraction groups ("
                        f"{'; '.join(describe(g) for g in groups)}): choose one with "
                        "--fraction-group N (fraction_group = N in plan.toml)")
    chosen = groups[0] if number is None else next(
        (g for g in groups if int(g.FractionGroupNumber) == int(number)), None)
    if chosen is None:
        raise PlanError(f"{path} has no fraction group {number}; it has "
                        f"{'; '.join(describe(g) for g in groups)}")
    if int(chosen.get("NumberOfBrachyApplicationSetups", 0) or 0) > 0:
        raise PlanError(f"{path}: fraction group {describe(chosen)} has brachy application "
                        "setups: only external photon beams are modelled")
    return {int(r.ReferencedBeamNumber): r.get("BeamMeterset")
            for r in chosen.get("ReferencedBeamSequence", [])}


def _refuse(beam: Dataset, name: str) -> None:
    """PlanError naming what tetdose does not model in ``beam``."""
    radiation = beam.get("RadiationType", "PHOTON") or "PHOTON"
    if radiation != "PHOTON":
        raise PlanError(f"RT Plan beam {name!r} is {radiation}: only photon beams are modelled")
    for key, what in (("NumberOfWedges", "wedges"), ("NumberOfBlocks", "blocks"),
                      ("NumberOfCompensators", "compensators"), ("NumberOfBoli", "boli")):
        if int(beam.get(key, 0) or 0) > 0:
            raise PlanError(f"RT Plan beam {name!r} has {what}: tetdose models jaws and one MLC "
                            "only; remove them or compute this beam elsewhere")
    for key, what in (("WedgeSequence", "wedges"), ("BlockSequence", "blocks"),
                      ("CompensatorSequence", "compensators"),
                      ("ReferencedBolusSequence", "boli"), ("ApplicatorSequence", "an applicator")):
        if len(beam.get(key, []) or []) > 0:
            raise PlanError(f"RT Plan beam {name!r} has {what}: tetdose models jaws and one MLC "
                            "only; remove them or compute this beam elsewhere")
    kinds = [str(d.RTBeamLimitingDeviceType) for d in beam.get("BeamLimitingDeviceSequence", [])]
    other = [k for k in kinds if k not in DEVICE_TYPES]
    if other:
        raise PlanError(f"RT Plan beam {name!r}: beam limiting device {other[0]} is not "
                        f"modelled ({', '.join(DEVICE_TYPES)})")
    if "MLCX" in kinds and "MLCY" in kinds:
        raise PlanError(f"RT Plan beam {name!r} has two MLCs (MLCX and MLCY): one is modelled")
    if beam.get("BeamType", "STATIC") not in ("STATIC", "DYNAMIC"):
        raise PlanError(f"RT Plan beam {name!r}: BeamType {beam.get('BeamType')!r} is neither "
                        "STATIC nor DYNAMIC")


def _beam_meterset(raw: Any, name: str) -> float:  # noqa: ANN401
    if raw is None or raw == "":
        raise PlanError(f"RT Plan beam {name!r}: the fraction group gives no BeamMeterset (MU)")
    mu = float(raw)
    if not (math.isfinite(mu) and mu > 0.0):
        raise PlanError(f"RT Plan beam {name!r}: BeamMeterset = {mu:g} MU; a treatment beam "
                        "needs a positive meterset")
    return mu


def _read_beam(beam: Dataset, setups: dict[int, str], raw_meterset: Any  # noqa: ANN401
               ) -> LinacBeam:
    name = str(beam.get("BeamName", "") or beam.BeamNumber)
    _refuse(beam, name)
    meterset = _beam_meterset(raw_meterset, name)
    sad = float(beam.get("SourceAxisDistance", 1000.0) or 1000.0)
    if sad < MIN_SAD_MM:
        raise PlanError(f"RT Plan beam {name!r}: SourceAxisDistance = {sad:g} mm is below "
                        f"{MIN_SAD_MM:g} mm (a linac's is 800–1000 mm)")
    leaves = None
    for dev in beam.get("BeamLimitingDeviceSequence", []):
        if dev.RTBeamLimitingDeviceType in ("MLCX", "MLCY"):
            if not dev.get("LeafPositionBoundaries"):
                raise PlanError(f"RT Plan beam {name!r}: {dev.RTBeamLimitingDeviceType} has no "
                                "LeafPositionBoundaries")
            leaves = (str(dev.RTBeamLimitingDeviceType),
                      [float(v) for v in dev.LeafPositionBoundaries])
    points, iso, energy = _control_points(beam, name, leaves)
    position = _patient_position(beam, setups, name)
    spectrum, mode = _spectrum(beam, name, energy)
    final = beam.get("FinalCumulativeMetersetWeight")
    last = points[-1].meterset_weight
    if final not in (None, "") and abs(float(final) - last) > 1e-6 * max(abs(last), 1.0):
        raise PlanError(f"RT Plan beam {name!r}: FinalCumulativeMetersetWeight {float(final):g} "
                        f"differs from the last control point's CumulativeMetersetWeight "
                        f"{last:g}")
    try:
        out = LinacBeam(name, spectrum, iso, tuple(points), sad, position, meterset,
                        fluence_mode=mode)
    except PlanError as exc:
        raise PlanError(f"RT Plan {exc}") from None
    if beam.get("BeamType", "STATIC") == "STATIC" and _moves(out):
        warnings.warn(f"RT Plan beam {name!r} is STATIC but its control points move while the "
                      "beam is on; computed as they say (as a DYNAMIC beam)", stacklevel=4)
    odd = _odd_turn(out)
    if odd:
        warnings.warn(f"RT Plan beam {name!r} {odd}", stacklevel=4)
    return out


def _odd_turn(beam: LinacBeam) -> str:
    """What is odd about the first rotation of ``beam`` that the plan states oddly: a full turn
    between equal angles (C.8.8.14.8 example 2) or a change of angle with direction NONE; ""."""
    cps = beam.control_points
    for k, (a, b) in enumerate(zip(cps[:-1], cps[1:], strict=True)):
        if b.meterset_weight <= a.meterset_weight:
            continue
        for axis, turn in zip(("gantry", "collimator", "couch"), a.turns_deg(b), strict=True):
            start, stop = getattr(a, f"{axis}_deg"), getattr(b, f"{axis}_deg")
            direction = getattr(a, f"{axis}_rotation")
            if abs(turn) == 360.0:
                return (f"turns the {axis} a full 360° {direction} between control points {k} "
                        f"and {k + 1} (equal angles {start:g}° with direction {direction}, DICOM "
                        f"C.8.8.14.8); if the {axis} stands still, its rotation direction must "
                        "be NONE (or the angle omitted after control point 0)")
            if direction == "NONE" and turn != 0.0:
                return (f"control point {k} has {axis} rotation direction NONE but the angle "
                        f"moves {start:g}° → {stop:g}° while the beam is on: computed as the "
                        f"shorter turn ({turn:+g}°); give CW or CC to say otherwise")
    return ""


def _moves(beam: LinacBeam) -> bool:
    cps = beam.control_points
    return any(not same_state(a, b) for a, b in zip(cps[:-1], cps[1:], strict=True)
               if b.meterset_weight > a.meterset_weight)


def _patient_position(beam: Dataset, setups: dict[int, str], name: str) -> str:
    number = beam.get("ReferencedPatientSetupNumber")
    if not setups:
        warnings.warn("the RT Plan has no PatientSetupSequence: patient position HFS assumed",
                      stacklevel=5)
        return "HFS"
    pos = setups.get(int(number)) if number is not None else next(iter(setups.values()))
    if pos not in ("HFS", "HFP", "FFS", "FFP"):
        raise PlanError(f"RT Plan beam {name!r}: patient position {pos!r} is not modelled "
                        "(HFS, HFP, FFS, FFP)")
    return pos


def _spectrum(beam: Dataset, name: str, energy_mv: float) -> tuple[str, str]:
    """(named spectrum, fluence mode "STANDARD" | "FFF") of a beam (see module doc)."""
    from tetdose.plan.spectra import NAMED_SPECTRA, is_named, named_spectrum

    mode = "STANDARD"
    for item in beam.get("PrimaryFluenceModeSequence", [])[:1]:
        if item.get("FluenceMode", "STANDARD") == "NON_STANDARD":
            ident = str(item.get("FluenceModeID", "") or "")
            if ident.upper() not in ("FFF", "FF", "FFFB"):
                raise PlanError(f"RT Plan beam {name!r}: fluence mode {ident!r} is not modelled "
                                "(STANDARD, FFF)")
            mode = "FFF"
    spectrum = "Co60" if energy_mv <= 1.5 else f"{energy_mv:g}MV"
    if not is_named(spectrum):
        shipped = [n for n in NAMED_SPECTRA if n.endswith("MV")]
        raise PlanError(f"RT Plan beam {name!r}: NominalBeamEnergy {energy_mv:g} MV has no "
                        f"shipped spectrum ({', '.join(shipped)}, Co60); give the beam in "
                        "plan.toml with spectrum = \"file.csv\"")
    try:
        named_spectrum(spectrum)
    except PlanError as exc:
        raise PlanError(f"RT Plan beam {name!r}: {exc}") from None
    if mode == "FFF":
        warnings.warn(f"RT Plan beam {name!r} is flattening-filter-free (FFF): computed with the "
                      f"flattened {spectrum} spectrum and a flat fluence (the FFF beam's softer "
                      "spectrum and centre-peaked profile are not modelled)", stacklevel=5)
    return spectrum, mode


_ANGLES = (("gantry_deg", "GantryAngle"), ("collimator_deg", "BeamLimitingDeviceAngle"),
           ("couch_deg", "PatientSupportAngle"))
_DIRECTIONS = (("gantry_rotation", "GantryRotationDirection"),
               ("collimator_rotation", "BeamLimitingDeviceRotationDirection"),
               ("couch_rotation", "PatientSupportRotationDirection"))


def _control_points(beam: Dataset, name: str, leaves: tuple[str, list[float]] | None
                    ) -> tuple[list[ControlPoint], list[float], float]:
    """(control points, isocentre of the first, nominal energy [MV]) of a beam."""
    seq = beam.get("ControlPointSequence")
    if not seq:
        raise PlanError(f"RT Plan beam {name!r} has no ControlPointSequence")
    static = beam.get("BeamType", "STATIC") == "STATIC"
    state: dict[str, Any] = {"jaws_mm": [-OPEN_JAW_MM, OPEN_JAW_MM, -OPEN_JAW_MM, OPEN_JAW_MM],
                             "mlc": None, "gantry_rotation": "NONE",
                             "collimator_rotation": "NONE", "couch_rotation": "NONE",
                             "collimator_deg": 0.0, "couch_deg": 0.0}
    iso = energy = None
    points = []
    given = [{key for key, tag in _ANGLES if cp.get(tag) not in (None, "")} for cp in seq]
    for k, cp in enumerate(seq):
        where = f"RT Plan beam {name!r} control point {k}"
        weight = cp.get("CumulativeMetersetWeight")
        if weight is None or weight == "":
            raise PlanError(f"{where} has no CumulativeMetersetWeight")
        for key, tag in _ANGLES:
            if key in given[k]:
                state[key] = float(cp.get(tag))
        for key, tag in _DIRECTIONS:
            if cp.get(tag) not in (None, ""):
                state[key] = "NONE" if static else str(cp.get(tag))
        if cp.get("NominalBeamEnergy") not in (None, ""):
            e = float(cp.NominalBeamEnergy)
            if energy is not None and e != energy:
                raise PlanError(f"{where} changes NominalBeamEnergy from {energy:g} to {e:g} MV: "
                                "split the beam by energy")
            energy = e
        if cp.get("IsocenterPosition"):
            state["isocenter_mm"] = [float(v) for v in cp.IsocenterPosition]
        for tag in ("TableTopPitchAngle", "TableTopRollAngle", "TableTopEccentricAngle"):
            if cp.get(tag) not in (None, "") and abs(float(cp.get(tag))) > 1e-6:
                raise PlanError(f"{where} has {tag} {float(cp.get(tag)):g}°: table-top pitch, "
                                "roll and eccentric rotation are not modelled")
        try:
            _devices(cp, state, leaves)
        except PlanError as exc:
            raise PlanError(f"{where}: {exc}") from None
        if k == 0:
            if "gantry_deg" not in state or "isocenter_mm" not in state or energy is None:
                raise PlanError(f"{where} (the first) lacks GantryAngle, IsocenterPosition or "
                                "NominalBeamEnergy")
            if leaves is not None and state["mlc"] is None:
                raise PlanError(f"{where} (the first) gives no {leaves[0]} leaf positions")
            iso = state["isocenter_mm"]
        # An angle the next control point omits is unchanged (C.8.8.14.5): no turn towards it,
        # whatever rotation direction is carried forward.
        still = {f"{key[:-4]}_rotation": "NONE" for key, _tag in _ANGLES
                 if k + 1 < len(seq) and key not in given[k + 1]}
        try:
            points.append(ControlPoint(**dict(state, meterset_weight=float(weight), **still)))
        except PlanError as exc:
            raise PlanError(f"{where}: {exc}") from None
    return points, list(iso), float(energy)


def _devices(cp: Dataset, state: dict[str, Any], leaves: tuple[str, list[float]] | None
             ) -> None:
    """Carry a control point's jaw and leaf positions into ``state``."""
    jaws = list(state["jaws_mm"])
    for dev in cp.get("BeamLimitingDevicePositionSequence", []):
        kind = dev.RTBeamLimitingDeviceType
        p = [float(v) for v in dev.LeafJawPositions]
        if kind in ("X", "ASYMX", "Y", "ASYMY") and len(p) != 2:
            raise PlanError(f"{kind} needs 2 LeafJawPositions, got {len(p)}")
        if kind in ("X", "ASYMX"):
            jaws[0:2] = p
        elif kind in ("Y", "ASYMY"):
            jaws[2:4] = p
        elif leaves is not None and kind == leaves[0]:
            n = len(leaves[1]) - 1
            if len(p) != 2 * n:
                raise PlanError(f"{kind} has {len(p)} LeafJawPositions, its "
                                f"{n} leaf pairs need {2 * n}")
            state["mlc"] = MLC(leaves[1], p, kind[-1])
        elif kind in ("MLCX", "MLCY"):
            raise PlanError(f"{kind} positions without the device in the beam's "
                            "BeamLimitingDeviceSequence")
    state["jaws_mm"] = jaws
