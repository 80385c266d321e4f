"""Who and what a DICOM series belongs to: patient, study and frame of reference.

A scan is one study and one frame of reference: every reconstruction of it (FDK, SART, the
Gaussian methods) is a series of that study, and all of them share its ``FrameOfReferenceUID``,
since they lie on the same world points. The identity of a scan comes from:

* the DICOM CT it was simulated from (``clgs simulate`` records that series' patient, study and
  frame of reference in ``scan.json``'s ``meta.dicom_source``, read by :func:`read_dicom_identity`):
  the reconstructions join the patient's own study, in the input's frame of reference;
* otherwise an anonymous identity (:func:`anonymous_identity`): patient ``ANONYMOUS^CLGS`` with an
  ID, study and frame UIDs all derived from the scan's data (its geometry and projections), and
  the study date and time of the scan's making (``meta.provenance.created``), left empty (DICOM
  Type 2) where a scan does not record it.

Nothing here reads the clock: the same scan gives the same identity, and so the same files.
UIDs live under the ``2.25`` root (a UUID-derived UID: no registered organisation root needed),
made from a SHA-256 digest.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from clgs.errors import ClgsError

__all__ = ["DicomIdentityError", "derived_uid", "scan_digest", "scan_identity", "anonymous_identity",
           "read_dicom_identity", "input_identity", "CARRIED", "ANONYMOUS_NAME"]

ANONYMOUS_NAME = "ANONYMOUS^CLGS"
#: the attributes carried from a DICOM input to every series made from it (patient, study, frame)
CARRIED = ("PatientName", "PatientID", "IssuerOfPatientID", "PatientBirthDate", "PatientSex", "PatientAge",
           "StudyInstanceUID", "StudyDate", "StudyTime", "StudyID", "AccessionNumber",
           "ReferringPhysicianName", "StudyDescription", "FrameOfReferenceUID", "PositionReferenceIndicator",
           "PatientPosition", "PatientIdentityRemoved", "DeidentificationMethod")


class DicomIdentityError(ClgsError, ValueError):
    """A DICOM input whose identity cannot be read."""


def derived_uid(*parts) -> str:
    """A UID under the root 2.25 (the decimal of 128 bits), from a digest of ``parts``."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else str(p).encode())
        h.update(b"\0")
    return "2.25." + str(int.from_bytes(h.digest()[:16], "big"))


def scan_digest(scan) -> str:
    """SHA-256 (hex) of what a scan measured: its geometry (canonical JSON) and its projections
    (float32). Two folders holding the same scan share it; a file's dates do not enter it."""
    h = hashlib.sha256()
    h.update(json.dumps(scan.geometry.to_dict(), sort_keys=True, separators=(",", ":")).encode())
    proj = np.ascontiguousarray(scan.projections, dtype=np.float32)
    h.update(str(proj.shape).encode())
    h.update(memoryview(proj).cast("B"))
    return h.hexdigest()


def _dicom_date_time(stamp) -> tuple:
    """('YYYYMMDD', 'HHMMSS') of an ISO 8601 time stamp (e.g. ``2025-03-01T12:30:05Z``), or ('', '')."""
    import datetime

    if not isinstance(stamp, str) or not stamp:
        return "", ""
    try:
        t = datetime.datetime.fromisoformat(stamp.replace("Z", "+00:00"))
    except ValueError:
        return "", ""
    return t.strftime("%Y%m%d"), t.strftime("%H%M%S")


def anonymous_identity(digest: str, created=None) -> dict:
    """The identity of data with no patient: ``ANONYMOUS^CLGS``, a patient ID, study and frame
    UIDs from ``digest``; study date and time from ``created`` (ISO 8601) or empty."""
    date, time = _dicom_date_time(created)
    return {
        "PatientName": ANONYMOUS_NAME, "PatientID": f"CLGS-{digest[:12].upper()}", "PatientBirthDate": "",
        "PatientSex": "", "StudyInstanceUID": derived_uid("study", digest),
        "StudyDate": date, "StudyTime": time, "StudyID": digest[:8].upper(), "AccessionNumber": "",
        "ReferringPhysicianName": "", "FrameOfReferenceUID": derived_uid("frame-of-reference", digest),
        "PositionReferenceIndicator": "",
    }


def scan_identity(scan) -> dict:
    """The identity every series made from ``scan`` (a :class:`clgs.io.scan.Scan`) carries: the
    DICOM input's (``meta.dicom_source``) over the anonymous one; ``scan_digest`` added."""
    digest = scan_digest(scan)
    meta = scan.meta if isinstance(scan.meta, dict) else {}
    prov = meta.get("provenance") if isinstance(meta.get("provenance"), dict) else {}
    ident = anonymous_identity(digest, prov.get("created"))
    source = meta.get("dicom_source")
    if isinstance(source, dict):
        ident.update({k: str(v) for k, v in source.items() if k in CARRIED and isinstance(v, (str, int, float))})
    ident["scan_digest"] = digest
    return ident


def _series_file(path: Path) -> Path:
    """One file of the DICOM series at ``path`` (a folder of slices, or one of its files)."""
    if path.is_file():
        return path
    import pydicom

    for f in sorted(p for p in path.iterdir() if p.is_file()):
        try:
            pydicom.dcmread(f, stop_before_pixels=True, specific_tags=["SOPClassUID"])
        except Exception:  # noqa: BLE001 - not a DICOM file: the next one
            continue
        return f
    raise DicomIdentityError(f"{path}: no DICOM file found")


def read_dicom_identity(path) -> dict:
    """The patient, study and frame-of-reference attributes (:data:`CARRIED`) of a DICOM series,
    as strings (empty ones kept: they are known to be empty). Needs pydicom (the ``formats``
    extra)."""
    try:
        import pydicom
    except ImportError as exc:
        raise DicomIdentityError("reading a DICOM input's patient and study needs pydicom: "
                                 "pip install 'clgs[formats]' (the set-up installs it)") from exc
    f = _series_file(Path(path))
    try:
        ds = pydicom.dcmread(f, stop_before_pixels=True)
    except Exception as exc:  # noqa: BLE001 - pydicom's message says what it could not read
        raise DicomIdentityError(f"{f}: not a readable DICOM file ({exc})") from exc
    found = {}
    for k in CARRIED:
        if k in ds:
            v = getattr(ds, k)
            found[k] = "" if v is None else str(v)
    return found


def input_identity(path) -> dict | None:
    """:func:`read_dicom_identity` of a volume input that is a DICOM series (a folder of slices or a
    ``.dcm`` file); None for any other file (NIfTI, MetaImage, NRRD, ``.npy``)."""
    path = Path(path)
    if not (path.is_dir() or path.name.lower().endswith(".dcm")):
        return None
    return read_dicom_identity(path)
