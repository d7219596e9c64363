"""DICOM RT Plan (PS3.3 A.20) with photon beams: write tetdose's linac beams, read a TPS plan.

Written: Patient, General Study, RT Series, Frame of Reference, General Equipment, RT General
Plan (RTPlanGeometry TREATMENT_DEVICE: tetdose has no RT Structure Set to reference, which
PATIENT geometry requires; the isocentres are in the Frame of Reference of the CT), RT Patient
Setup, RT Fraction Scheme (BeamMeterset per beam), RT Beams and SOP Common. Every control point
of a beam is written (C.8.8.14.5): the first with every parameter, the later ones with each
parameter that changes anywhere in the beam (angles, rotation directions, isocentre, jaws as
ASYMX/ASYMY, leaves as MLCX/MLCY); a beam of one control point becomes the pair 0 → 1 of a
static field. BeamType is STATIC when nothing moves while the beam is on (static fields,
step-and-shoot), else DYNAMIC; the fluence mode (FFF) goes to PrimaryFluenceModeSequence.
Numbers are written as the shortest decimal string that reads back to the same float, so a plan
read from a file and written again reads back exactly.

Read: :func:`read_rt_plan_beams` (:mod:`tetdose.plan.rt_plan_read`), or
:meth:`tetdose.plan.model.Plan.from_rt_plan` for a whole :class:`Plan`.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import RTPlanStorage
from pydicom.valuerep import format_number_as_ds

from tetdose._atomic import atomic_write_file
from tetdose.dicom.modules import (
    StudyContext,
    rt_general_plan,
    save,
    set_equipment,
    study_context,
)
from tetdose.dicom.uid import DEFAULT_PREFIX, derive_uid
from tetdose.errors import DicomError
from tetdose.plan.beams import ControlPoint, LinacBeam, same_state
from tetdose.plan.rt_plan_read import read_rt_plan_beams

__all__ = ["plan_dataset", "read_rt_plan_beams", "write_rt_plan"]

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
    seed = repr([(b.name, b.spectrum, b.isocenter_mm.tolist(), len(b.control_points))
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
    """A Decimal String (≤ 16 characters) that reads back to ``x``: the shortest repr when it
    fits, else pydicom's 16-character rounding."""
    r = repr(float(x) + 0.0)  # + 0.0: no "-0.0"
    r = r[:-2] if r.endswith(".0") else r
    return r if len(r) <= 16 else format_number_as_ds(float(x))


def _beam_item(b: LinacBeam, number: int, setup: int) -> Dataset:
    from tetdose.plan.spectra import canonical_name

    cps = list(b.control_points)
    if len(cps) == 1:  # a static field: the pair 0 → 1 of the same state
        cps = [replace(cps[0], meterset_weight=0.0), replace(cps[0], meterset_weight=1.0)]
    mlc = cps[0].mlc
    devices = [_item(RTBeamLimitingDeviceType="ASYMX", NumberOfLeafJawPairs=1),
               _item(RTBeamLimitingDeviceType="ASYMY", NumberOfLeafJawPairs=1)]
    if mlc is not None:
        dev = _item(RTBeamLimitingDeviceType=f"MLC{mlc.axis}",
                    NumberOfLeafJawPairs=len(mlc.boundaries_mm) - 1)
        dev.LeafPositionBoundaries = [_ds(v) for v in mlc.boundaries_mm]
        devices.append(dev)
    moving = any(not same_state(p, q) for p, q in zip(cps[:-1], cps[1:], strict=True)
                 if q.meterset_weight > p.meterset_weight)
    item = _item(BeamNumber=number, BeamName=b.name[:64], BeamType="DYNAMIC" if moving else
                 "STATIC", RadiationType="PHOTON", TreatmentMachineName="tetdose linac",
                 PrimaryDosimeterUnit="MU", SourceAxisDistance=_ds(b.sad_mm),
                 TreatmentDeliveryType="TREATMENT", NumberOfWedges=0, NumberOfCompensators=0,
                 NumberOfBoli=0, NumberOfBlocks=0,
                 FinalCumulativeMetersetWeight=_ds(cps[-1].meterset_weight),
                 NumberOfControlPoints=len(cps), ReferencedPatientSetupNumber=setup)
    if b.fluence_mode != "STANDARD":
        item.PrimaryFluenceModeSequence = [_item(FluenceMode="NON_STANDARD",
                                                 FluenceModeID=b.fluence_mode)]
    else:
        item.PrimaryFluenceModeSequence = [_item(FluenceMode="STANDARD")]
    item.BeamLimitingDeviceSequence = devices
    values = [_cp_values(b, cp) for cp in cps]
    changing = {k for k in values[0] if any(v[k] != values[0][k] for v in values[1:])}
    # A full turn between equal angles is a change: an omitted angle would read as unchanged.
    turns = np.array([p.turns_deg(q) for p, q in zip(cps[:-1], cps[1:], strict=True)])
    changing |= {key for key, t in zip(("GantryAngle", "BeamLimitingDeviceAngle",
                                        "PatientSupportAngle"), turns.T, strict=True) if t.any()}
    item.ControlPointSequence = [_control_point(b, v, k, changing) for k, v in enumerate(values)]
    item.BeamDescription = (f"{canonical_name(b.spectrum) or Path(b.spectrum).name} "
                            "(tetdose spectrum)")
    return item


def _cp_values(b: LinacBeam, cp: ControlPoint) -> dict[str, Any]:  # noqa: ANN401
    """The DICOM values of one control point, as strings (compared to find what changes)."""
    out: dict[str, Any] = {
        "GantryAngle": _ds(cp.gantry_deg % 360.0), "GantryRotationDirection": cp.gantry_rotation,
        "BeamLimitingDeviceAngle": _ds(cp.collimator_deg % 360.0),
        "BeamLimitingDeviceRotationDirection": cp.collimator_rotation,
        "PatientSupportAngle": _ds(cp.couch_deg % 360.0),
        "PatientSupportRotationDirection": cp.couch_rotation,
        "IsocenterPosition": [_ds(v) for v in b.isocenter_at(cp)],
        "ASYMX": [_ds(v) for v in cp.jaws_mm[:2]], "ASYMY": [_ds(v) for v in cp.jaws_mm[2:]],
        "weight": _ds(cp.meterset_weight)}
    if cp.mlc is not None:
        out[f"MLC{cp.mlc.axis}"] = [_ds(v) for v in cp.mlc.positions_mm]
    return out


def _control_point(b: LinacBeam, values: dict[str, Any], index: int, changing: set[str]
                   ) -> Dataset:  # noqa: ANN401
    from tetdose.plan.spectra import canonical_name

    cp = _item(ControlPointIndex=index, CumulativeMetersetWeight=values["weight"])
    if index == 0:
        # A spectrum file: its highest energy stands for the nominal MV (endpoint).
        cp.NominalBeamEnergy = _ds(_NOMINAL_MV.get(str(canonical_name(b.spectrum)),
                                                   round(max(float(e) for e in b.energies_mev), 1)))
        cp.TableTopEccentricAngle = "0"  # DS
        cp.TableTopPitchAngle = 0.0  # FL
        cp.TableTopRollAngle = 0.0  # FL
        for key in ("TableTopEccentricRotationDirection", "TableTopPitchRotationDirection",
                    "TableTopRollRotationDirection"):
            setattr(cp, key, "NONE")
        for key in ("TableTopVerticalPosition", "TableTopLongitudinalPosition",
                    "TableTopLateralPosition"):
            setattr(cp, key, None)
    for key in ("GantryAngle", "GantryRotationDirection", "BeamLimitingDeviceAngle",
                "BeamLimitingDeviceRotationDirection", "PatientSupportAngle",
                "PatientSupportRotationDirection", "IsocenterPosition"):
        if index == 0 or key in changing:
            setattr(cp, key, values[key])
    devices = [_item(RTBeamLimitingDeviceType=k, LeafJawPositions=values[k])
               for k in ("ASYMX", "ASYMY", "MLCX", "MLCY")
               if k in values and (index == 0 or k in changing)]
    if devices:
        cp.BeamLimitingDevicePositionSequence = devices
    return cp
