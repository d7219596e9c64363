"""A VMAT RT Plan built with pydicom to the standard (PS3.3 A.20), as a planning system writes it:
two arcs (181° → 179° CW, then back CC) of 91 control points each with a 60-pair MLCX (10 mm
outer, 5 mm inner leaves), jaws at the first control point only, and later control points
giving only what changes (GantryAngle, CumulativeMetersetWeight, MLCX positions; C.8.8.14.5)."""

from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, RTPlanStorage, generate_uid

#: Leaf boundaries of a 120-leaf MLC [mm]: 10 × 10 mm, 40 × 5 mm, 10 × 10 mm.
BOUNDARIES_MM = np.concatenate([np.arange(-200, -100, 10), np.arange(-100, 100, 5),
                                np.arange(100, 201, 10)]).astype(float)


def _item(**kw):
    ds = Dataset()
    for k, v in kw.items():
        setattr(ds, k, v)
    return ds


def _leaves(k, n_cp, arc):
    """Bank positions of control point k: an opening of 20–60 mm that sweeps and breathes."""
    n = len(BOUNDARIES_MM) - 1
    y = 0.5 * (BOUNDARIES_MM[:-1] + BOUNDARIES_MM[1:])
    phase = 2 * np.pi * k / (n_cp - 1) + arc
    centre = 15 * np.sin(phase + y / 40)
    half = 10 + 20 * (0.5 + 0.5 * np.cos(phase)) * np.exp(-(y / 60) ** 2)
    closed = np.abs(y) > 70  # leaves outside the target meet under the jaws
    lo = np.where(closed, -0.5, centre - half)
    hi = np.where(closed, 0.5, centre + half)
    return [f"{v:.2f}" for v in np.concatenate([lo, hi])], n


def _arc(number, name, start, stop, direction, n_cp, iso, arc):
    sign = 1.0 if direction == "CW" else -1.0
    step = ((sign * (stop - start)) % 360.0) / (n_cp - 1)
    beam = _item(BeamNumber=number, BeamName=name, BeamType="DYNAMIC", RadiationType="PHOTON",
                 TreatmentMachineName="TrueBeam", PrimaryDosimeterUnit="MU",
                 SourceAxisDistance="1000", TreatmentDeliveryType="TREATMENT",
                 NumberOfWedges=0, NumberOfCompensators=0, NumberOfBoli=0, NumberOfBlocks=0,
                 FinalCumulativeMetersetWeight="1", NumberOfControlPoints=n_cp,
                 ReferencedPatientSetupNumber=1, Manufacturer="test")
    beam.PrimaryFluenceModeSequence = [_item(FluenceMode="STANDARD")]
    mlc = _item(RTBeamLimitingDeviceType="MLCX", NumberOfLeafJawPairs=len(BOUNDARIES_MM) - 1)
    mlc.LeafPositionBoundaries = [f"{v:g}" for v in BOUNDARIES_MM]
    beam.BeamLimitingDeviceSequence = [
        _item(RTBeamLimitingDeviceType="ASYMX", NumberOfLeafJawPairs=1),
        _item(RTBeamLimitingDeviceType="ASYMY", NumberOfLeafJawPairs=1), mlc]
    cps = []
    for k in range(n_cp):
        leaves, _ = _leaves(k, n_cp, arc)
        cp = _item(ControlPointIndex=k, CumulativeMetersetWeight=f"{k / (n_cp - 1):.6g}",
                   GantryAngle=f"{(start + sign * k * step) % 360.0:.6g}")
        pos = [_item(RTBeamLimitingDeviceType="MLCX", LeafJawPositions=leaves)]
        if k == 0:
            cp.NominalBeamEnergy = "6"
            cp.DoseRateSet = "600"
            cp.GantryRotationDirection = direction
            cp.BeamLimitingDeviceAngle = "30" if arc == 0 else "330"
            cp.BeamLimitingDeviceRotationDirection = "NONE"
            cp.PatientSupportAngle = "0"
            cp.PatientSupportRotationDirection = "NONE"
            cp.TableTopEccentricAngle = "0"
            cp.TableTopEccentricRotationDirection = "NONE"
            cp.TableTopPitchAngle = 0.0
            cp.TableTopPitchRotationDirection = "NONE"
            cp.TableTopRollAngle = 0.0
            cp.TableTopRollRotationDirection = "NONE"
            cp.TableTopVerticalPosition = None
            cp.TableTopLongitudinalPosition = None
            cp.TableTopLateralPosition = None
            cp.IsocenterPosition = [f"{v:g}" for v in iso]
            pos = [_item(RTBeamLimitingDeviceType="ASYMX", LeafJawPositions=["-45", "45"]),
                   _item(RTBeamLimitingDeviceType="ASYMY", LeafJawPositions=["-80", "80"]), *pos]
        elif k == n_cp - 1:
            cp.GantryRotationDirection = "NONE"
        cp.BeamLimitingDevicePositionSequence = pos
        cps.append(cp)
    beam.ControlPointSequence = cps
    return beam


def write_vmat_plan(path: Path, iso=(0.0, 0.0, 0.0), n_cp: int = 91,
                    metersets=(310.5, 295.25)) -> Path:
    """Write the VMAT plan (see module doc) with isocentre ``iso`` [mm]; return ``path``."""
    uid = generate_uid(entropy_srcs=["tetdose-test-vmat", str(path.name)])
    ds = Dataset()
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID, ds.SOPInstanceUID = RTPlanStorage, uid
    for key in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate",
                "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber",
                "OperatorsName"):
        setattr(ds, key, "")
    ds.PatientName, ds.PatientID = "VMAT^Test", "VMAT01"
    ds.Modality, ds.Manufacturer = "RTPLAN", "test"
    ds.StudyInstanceUID = generate_uid(entropy_srcs=["study", uid])
    ds.SeriesInstanceUID = generate_uid(entropy_srcs=["series", uid])
    ds.SeriesNumber, ds.InstanceNumber = 1, 1
    ds.FrameOfReferenceUID = generate_uid(entropy_srcs=["frame", uid])
    ds.PositionReferenceIndicator = ""
    ds.RTPlanLabel, ds.RTPlanName = "VMAT", "VMAT two arcs"
    ds.RTPlanDate, ds.RTPlanTime = "20240101", "120000"
    ds.RTPlanGeometry = "TREATMENT_DEVICE"
    ds.ApprovalStatus = "UNAPPROVED"
    ds.PatientSetupSequence = [_item(PatientPosition="HFS", PatientSetupNumber=1,
                                     SetupTechnique="ISOCENTRIC")]
    fg = _item(FractionGroupNumber=1, NumberOfFractionsPlanned=30, NumberOfBeams=2,
               NumberOfBrachyApplicationSetups=0)
    fg.ReferencedBeamSequence = [_item(ReferencedBeamNumber=i + 1, BeamMeterset=f"{mu:g}")
                                 for i, mu in enumerate(metersets)]
    ds.FractionGroupSequence = [fg]
    ds.BeamSequence = [_arc(1, "ARC1", 181.0, 179.0, "CW", n_cp, iso, 0),
                       _arc(2, "ARC2", 179.0, 181.0, "CC", n_cp, iso, 1)]
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = RTPlanStorage, uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.save_as(path, enforce_file_format=True)
    return path
