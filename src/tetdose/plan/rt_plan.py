"""DICOM RT Plan (PS3.3 A.20) with photon beams: write tetdose's linac beams, read a TPS plan.

Written: Patient, General Study, RT Series, Frame of Reference, General Equipment, RT General
Plan (RTPlanGeometry TREATMENT_DEVICE: tetdose has no RT Structure Set to reference, which
PATIENT geometry requires; the isocentres are in the Frame of Reference of the CT), RT Patient
Setup, RT Fraction Scheme (BeamMeterset per beam), RT Beams and SOP Common. Each beam segment
becomes a pair of control points with the same aperture and cumulative meterset weights
w_k, w_{k+1} (step-and-shoot, C.8.8.14.1), jaws as ASYMX/ASYMY, MLC as MLCX.

Read (:func:`read_rt_plan_beams`, or :meth:`tetdose.plan.model.Plan.from_rt_plan` for a
whole :class:`Plan`): photon beams; nominal energy → named spectrum (≤ 1.5 MV: Co60,
else ``"<E>MV"``, which must be one of the shipped spectra); isocentre, gantry, collimator and
couch angles, X/ASYMX, Y/ASYMY jaws and MLCX leaves per control point, carried forward when a
control point omits them (C.8.8.14.5). Segment i (control points i → i+1) gets the meterset
weight ΔW_i = W_{i+1} − W_i of the beam's BeamMeterset (FractionGroupSequence); its angles are
the mean of the two control points' (arcs are sampled at their control points), its aperture
that of control point i. Refused with a PlanError naming the beam: non-photon radiation,
wedges, blocks, compensators, boli, MLCY.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import RTPlanStorage

from tetdose._atomic import atomic_write_file
from tetdose.dicom.modules import (
    StudyContext,
    rt_general_plan,
    save,
    set_equipment,
    study_context,
)
from tetdose.dicom.uid import DEFAULT_PREFIX, derive_uid
from tetdose.errors import DicomError, PlanError
from tetdose.plan.beams import MLC, ControlPoint, LinacBeam

if TYPE_CHECKING:  # the model reads RT Plans (Plan.from_rt_plan): no runtime import back
    from tetdose.plan.model import Plan

_NOMINAL_MV = {"Co60": 1.25, "Co60scatter": 1.25, "6MV": 6.0, "10MV": 10.0, "15MV": 15.0,
               "18MV": 18.0}


def write_rt_plan(plan: Plan, path: str | os.PathLike[str], *,
                  reference_ct: str | Path | None = None,
                  frame_of_reference_uid: str | None = None,
                  study_instance_uid: str | None = None, plan_uid: str | None = None,
                  series_number: int = 2001, uid_prefix: str | None = DEFAULT_PREFIX) -> Path:
    """Write the treatment beams of ``plan`` as an RT Plan at ``path`` (atomic); return it."""
    if not plan.treatment_beams or plan.unresolved:
        raise DicomError("an RT Plan needs linac beams with numeric isocentres; resolve "
                         "structure isocentres first (plan.resolved(geometry))")
    seed = repr([(b.name, b.spectrum, b.isocenter_mm.tolist(), len(b.segments))
                 for b in plan.treatment_beams])
    ctx = study_context(reference_ct, seed=seed, study_instance_uid=study_instance_uid,
                        frame_of_reference_uid=frame_of_reference_uid, uid_prefix=uid_prefix)
    plan_uid = plan_uid or derive_uid("rtplan", seed, ctx.frame_of_reference_uid,
                                      prefix=uid_prefix)
    path = Path(path)
    with atomic_write_file(path) as tmp:
        save(plan_dataset(plan, ctx, plan_uid, series_number), tmp, RTPlanStorage, plan_uid)
    return path


def plan_dataset(plan: Plan, ctx: StudyContext, plan_uid: str, number: int) -> Dataset:
    """The RT Plan dataset (every module but SOP Common, which :func:`save` adds)."""
    ds = Dataset()
    ctx.apply(ds)
    ds.Modality = "RTPLAN"
    ds.SeriesInstanceUID = derive_uid(plan_uid, "plan-series", prefix=ctx.uid_prefix)
    ds.SeriesNumber = int(number)
    ds.SeriesDescription = "tetdose treatment plan"
    ds.OperatorsName = ""
    set_equipment(ds)
    ds.InstanceNumber = 1
    rt_general_plan(ds, ctx, "tetdose", "tetdose linac beams")
    positions = sorted({b.patient_position for b in plan.treatment_beams})
    ds.PatientSetupSequence = [_item(PatientPosition=p, PatientSetupNumber=i + 1,
                                     SetupTechnique="ISOCENTRIC")
                               for i, p in enumerate(positions)]
    rx = plan.prescription
    fg = _item(FractionGroupNumber=1, NumberOfFractionsPlanned=rx.fractions if rx else 1,
               NumberOfBeams=len(plan.treatment_beams), NumberOfBrachyApplicationSetups=0)
    fg.ReferencedBeamSequence = [_item(ReferencedBeamNumber=i + 1, BeamMeterset=_ds(b.meterset))
                                 for i, b in enumerate(plan.treatment_beams)]
    ds.FractionGroupSequence = [fg]
    ds.BeamSequence = [_beam_item(b, i + 1, positions.index(b.patient_position) + 1)
                       for i, b in enumerate(plan.treatment_beams)]
    return ds


def _item(**kw: Any) -> Dataset:  # noqa: ANN401
    ds = Dataset()
    for k, v in kw.items():
        setattr(ds, k, v)
    return ds


def _ds(x: float) -> str:
    return f"{float(x):.10g}"


def _beam_item(b: LinacBeam, number: int, setup: int) -> Dataset:
    from tetdose.plan.spectra import canonical_name

    mlc = next((s.mlc for s in b.segments if s.mlc is not None), None)
    devices = [_item(RTBeamLimitingDeviceType="ASYMX", NumberOfLeafJawPairs=1),
               _item(RTBeamLimitingDeviceType="ASYMY", NumberOfLeafJawPairs=1)]
    if mlc is not None:
        dev = _item(RTBeamLimitingDeviceType="MLCX",
                    NumberOfLeafJawPairs=len(mlc.boundaries_mm) - 1)
        dev.LeafPositionBoundaries = [_ds(v) for v in mlc.boundaries_mm]
        devices.append(dev)
    total = sum(s.meterset_fraction for s in b.segments)
    cps, cum = [], 0.0
    for seg in b.segments:
        for w in (cum, cum + seg.meterset_fraction / total):
            cps.append(_control_point(b, seg, len(cps), w, mlc is not None))
        cum += seg.meterset_fraction / total
    item = _item(BeamNumber=number, BeamName=b.name[:64], BeamType="STATIC",
                 RadiationType="PHOTON", TreatmentMachineName="tetdose linac",
                 PrimaryDosimeterUnit="MU", SourceAxisDistance=_ds(b.sad_mm),
                 TreatmentDeliveryType="TREATMENT", NumberOfWedges=0, NumberOfCompensators=0,
                 NumberOfBoli=0, NumberOfBlocks=0, FinalCumulativeMetersetWeight="1",
                 NumberOfControlPoints=len(cps), ReferencedPatientSetupNumber=setup)
    item.BeamLimitingDeviceSequence = devices
    item.ControlPointSequence = cps
    item.BeamDescription = f"{canonical_name(b.spectrum) or Path(b.spectrum).name} (tetdose spectrum)"
    return item


def _control_point(b: LinacBeam, seg: ControlPoint, index: int, weight: float,
                   with_mlc: bool) -> Dataset:
    from tetdose.plan.spectra import canonical_name

    cp = _item(ControlPointIndex=index, CumulativeMetersetWeight=_ds(min(weight, 1.0)))
    if index == 0:
        # A spectrum file: its highest energy stands for the nominal MV (endpoint).
        cp.NominalBeamEnergy = _ds(_NOMINAL_MV.get(str(canonical_name(b.spectrum)),
                                                   round(max(float(e) for e in b.energies_mev), 1)))
        cp.IsocenterPosition = [_ds(v) for v in b.isocenter_mm]
        cp.TableTopEccentricAngle = "0"  # DS
        cp.TableTopPitchAngle = 0.0  # FL
        cp.TableTopRollAngle = 0.0  # FL
        for key in ("TableTopEccentricRotationDirection", "TableTopPitchRotationDirection",
                    "TableTopRollRotationDirection"):
            setattr(cp, key, "NONE")
        for key in ("TableTopVerticalPosition", "TableTopLongitudinalPosition",
                    "TableTopLateralPosition"):
            setattr(cp, key, None)
    cp.GantryAngle = _ds(seg.gantry_deg % 360.0)
    cp.GantryRotationDirection = "NONE"
    cp.BeamLimitingDeviceAngle = _ds(seg.collimator_deg % 360.0)
    cp.BeamLimitingDeviceRotationDirection = "NONE"
    cp.PatientSupportAngle = _ds(seg.couch_deg % 360.0)
    cp.PatientSupportRotationDirection = "NONE"
    j = seg.jaws_mm
    pos = [_item(RTBeamLimitingDeviceType="ASYMX", LeafJawPositions=[_ds(j[0]), _ds(j[1])]),
           _item(RTBeamLimitingDeviceType="ASYMY", LeafJawPositions=[_ds(j[2]), _ds(j[3])])]
    if with_mlc:
        if seg.mlc is None:
            raise DicomError(f"beam {b.name!r}: give every segment an MLC or none")
        pos.append(_item(RTBeamLimitingDeviceType="MLCX",
                         LeafJawPositions=[_ds(v) for v in seg.mlc.positions_mm]))
    cp.BeamLimitingDevicePositionSequence = pos
    return cp


def read_rt_plan_beams(path: str | os.PathLike[str]) -> tuple[LinacBeam, ...]:
    """The photon treatment beams of an RT Plan (see module doc for what is read)."""
    try:
        ds = pydicom.dcmread(path)
    except (OSError, InvalidDicomError) as exc:
        raise PlanError(f"cannot read RT Plan {path}: {exc}") from None
    if getattr(ds, "Modality", "") != "RTPLAN" or "BeamSequence" not in ds:
        raise PlanError(f"{path} is not an RT Plan with beams (Ion and brachy plans are not "
                        "supported)")
    setups = {int(s.PatientSetupNumber): str(s.get("PatientPosition", "HFS"))
              for s in ds.get("PatientSetupSequence", [])}
    meterset = {}
    for fg in ds.get("FractionGroupSequence", [])[:1]:
        for rb in fg.get("ReferencedBeamSequence", []):
            meterset[int(rb.ReferencedBeamNumber)] = float(rb.get("BeamMeterset", 1.0) or 1.0)
    beams = [_read_beam(b, setups, meterset) for b in ds.BeamSequence
             if b.get("TreatmentDeliveryType", "TREATMENT") == "TREATMENT"]
    beams = [b for b in beams if b is not None]
    if not beams:
        raise PlanError(f"{path}: no treatment beam with meterset to compute")
    return tuple(beams)


def _refuse(beam: Dataset) -> None:
    name = beam.get("BeamName", beam.get("BeamNumber", "?"))
    if beam.get("RadiationType", "PHOTON") != "PHOTON":
        raise PlanError(f"RT Plan beam {name!r} is {beam.RadiationType}: only photon beams are "
                        "modelled")
    for key in ("NumberOfWedges", "NumberOfBlocks", "NumberOfCompensators", "NumberOfBoli"):
        if int(beam.get(key, 0) or 0) > 0:
            raise PlanError(f"RT Plan beam {name!r} has {key[8:].lower()}: tetdose models jaws "
                            "and MLCX only; remove them or compute this beam elsewhere")
    for dev in beam.get("BeamLimitingDeviceSequence", []):
        if dev.RTBeamLimitingDeviceType not in ("X", "Y", "ASYMX", "ASYMY", "MLCX"):
            raise PlanError(f"RT Plan beam {name!r}: beam limiting device "
                            f"{dev.RTBeamLimitingDeviceType} is not modelled (X/Y jaws, MLCX)")


def _read_beam(beam: Dataset, setups: dict[int, str], meterset: dict[int, float]
               ) -> LinacBeam | None:
    _refuse(beam)
    number = int(beam.BeamNumber)
    if meterset.get(number, 1.0) <= 0.0:
        return None
    boundaries = None
    for dev in beam.get("BeamLimitingDeviceSequence", []):
        if dev.RTBeamLimitingDeviceType == "MLCX":
            boundaries = [float(v) for v in dev.LeafPositionBoundaries]
    state: dict[str, Any] = {"couch": 0.0, "coll": 0.0, "gantry": 0.0, "iso": None,
                             "energy": None, "jaws": [-200.0, 200.0, -200.0, 200.0], "mlc": None}
    points = []
    for cp in beam.ControlPointSequence:
        _update(state, cp)
        points.append(dict(state, w=float(cp.CumulativeMetersetWeight)))
    final = float(beam.get("FinalCumulativeMetersetWeight", points[-1]["w"]) or points[-1]["w"])
    segs = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        dw = (b["w"] - a["w"]) / final
        if dw <= 0.0:
            continue
        mlc = None if a["mlc"] is None or boundaries is None else MLC(boundaries, a["mlc"])
        segs.append(ControlPoint(_mean_angle(a["gantry"], b["gantry"]),
                                 _mean_angle(a["coll"], b["coll"]),
                                 _mean_angle(a["couch"], b["couch"]), a["jaws"], mlc, dw))
    name = str(beam.get("BeamName", number))
    if points[0]["iso"] is None or points[0]["energy"] is None:
        raise PlanError(f"RT Plan beam {name!r}: the first control point lacks "
                        "IsocenterPosition or NominalBeamEnergy")
    if not segs:
        return None
    e = points[0]["energy"]
    spectrum = "Co60" if e <= 1.5 else f"{e:g}MV"
    return LinacBeam(name, spectrum, points[0]["iso"], tuple(segs),
                     float(beam.get("SourceAxisDistance", 1000.0)),
                     setups.get(int(beam.get("ReferencedPatientSetupNumber", 1)), "HFS"),
                     meterset.get(number, 1.0))


def _update(state: dict[str, Any], cp: Dataset) -> None:
    """Carry a control point's attributes into ``state`` (absent ones keep their value)."""
    for key, tag in (("gantry", "GantryAngle"), ("coll", "BeamLimitingDeviceAngle"),
                     ("couch", "PatientSupportAngle"), ("energy", "NominalBeamEnergy")):
        if tag in cp and cp.get(tag) is not None:
            state[key] = float(cp.get(tag))
    if "IsocenterPosition" in cp:
        state["iso"] = [float(v) for v in cp.IsocenterPosition]
    jaws = list(state["jaws"])
    for dev in cp.get("BeamLimitingDevicePositionSequence", []):
        kind, p = dev.RTBeamLimitingDeviceType, [float(v) for v in dev.LeafJawPositions]
        if kind in ("X", "ASYMX"):
            jaws[0:2] = p
        elif kind in ("Y", "ASYMY"):
            jaws[2:4] = p
        elif kind == "MLCX":
            state["mlc"] = p
    state["jaws"] = jaws


def _mean_angle(a_deg: float, b_deg: float) -> float:
    """Mean of two angles along the shorter arc [deg]."""
    d = (b_deg - a_deg + 180.0) % 360.0 - 180.0
    return (a_deg + d / 2.0) % 360.0
