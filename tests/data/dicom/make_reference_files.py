#!/usr/bin/env python3
"""Makes the reference DICOM files of tests/dicom_encodings.rs with tools other than lungmotion.

Run once from the repository root (the outputs are committed):

    apt-get install -y dcmtk libgdcm-tools   # DCMTK 3.6.7, GDCM 3.0.21 when these were made
    pip install pydicom numpy                 # pydicom 3.0.2 when these were made
    python3 tests/data/dicom/make_reference_files.py ../shared/data/cip-chest-ct64/dicom

Input: four slices (IMG0040 … IMG0043, 64 × 64, int16 HU) of the public CIP chest CT.
Every output series gets its own SeriesInstanceUID, SeriesNumber and SeriesDescription so
that several can be copied into one folder (the "several series" tests).

| folder / file           | made by                                  | transfer syntax              |
| ----------------------- | ---------------------------------------- | ---------------------------- |
| native/                 | pydicom (copy, new series UID)           | explicit VR little endian    |
| jpegls-lossless/        | DCMTK dcmcjpls +el                       | 1.2.840.10008.1.2.4.80       |
| jpegls-near2/           | pydicom (HU + 1024 in 12 bits: DCMTK's   | 1.2.840.10008.1.2.4.81       |
|                         | near-lossless coder takes unsigned only) |                              |
|                         | then DCMTK dcmcjpls +en +md 2 (NEAR = 2) |                              |
| jpeg12/                 | pydicom (HU + 1024 in 12 bits) then      | 1.2.840.10008.1.2.4.51       |
|                         | DCMTK dcmcjpeg +ee +q 85                 |                              |
| j2k-lossy/              | GDCM gdcmconv --j2k --lossy -q 80        | 1.2.840.10008.1.2.4.91       |
| enhanced-ct.dcm         | pydicom: one Enhanced CT Image Storage   | explicit VR little endian    |
|                         | file, 4 frames in reverse order, per-    |                              |
|                         | frame Plane Position and Orientation,    |                              |
|                         | shared Pixel Measures and Pixel Value    |                              |
|                         | Transformation                           |                              |
| enhanced-ct-jpegls.dcm  | DCMTK dcmcjpls +el of enhanced-ct.dcm    | 1.2.840.10008.1.2.4.80       |
|                         | (one fragment a frame)                   |                              |
| enhanced-ct-j2k.dcm     | GDCM gdcmconv --j2k of enhanced-ct.dcm   | 1.2.840.10008.1.2.4.90       |
| *.reference-hu.i16le    | the lossy files decoded by their own     | HU, int16 little endian,     |
|                         | tool (dcmdjpeg, gdcmconv --raw), read    | slices in z order, i fastest |
|                         | with pydicom                             |                              |
"""
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

SLICES = ["IMG0040.dcm", "IMG0041.dcm", "IMG0042.dcm", "IMG0043.dcm"]
HERE = Path(__file__).resolve().parent
UID_ROOT = "1.2.826.0.1.3680043.10.1234."


def run(*args):
    subprocess.run([str(a) for a in args], check=True)


def restamp(ds, number, description, series_uid):
    """A series of its own: new series and instance UIDs, number and description."""
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = number
    ds.SeriesDescription = description
    ds.SOPInstanceUID = generate_uid(prefix=UID_ROOT)
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID


def write_series(sources, folder, number, description, transform=None):
    folder.mkdir(parents=True, exist_ok=True)
    uid = generate_uid(prefix=UID_ROOT)
    for src in sources:
        ds = pydicom.dcmread(src)
        restamp(ds, number, description, uid)
        if transform:
            transform(ds)
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.save_as(folder / src.name, enforce_file_format=True)


def to_12_bits(ds):
    """HU + 1024 stored unsigned in 12 bits, as 12-bit JPEG needs."""
    hu = ds.pixel_array.astype(np.int32)
    stored = np.clip(hu + 1024, 0, 4095).astype(np.uint16)
    ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 12, 11, 0
    ds.RescaleIntercept, ds.RescaleSlope = -1024, 1
    ds.PixelData = stored.tobytes()


def compress(folder_in, folder_out, *tool):
    folder_out.mkdir(parents=True, exist_ok=True)
    for f in sorted(folder_in.glob("*.dcm")):
        run(*tool, f, folder_out / f.name)


def reference_hu(folder, decompress, out_file):
    """Decodes with the tool that encoded, stores HU in z order."""
    with tempfile.TemporaryDirectory() as tmp:
        frames = []
        for f in sorted(folder.glob("*.dcm")):
            raw = Path(tmp) / f.name
            run(*decompress, f, raw)
            ds = pydicom.dcmread(raw)
            hu = ds.pixel_array.astype(np.float64) * float(ds.RescaleSlope) + float(
                ds.RescaleIntercept
            )
            frames.append((float(ds.ImagePositionPatient[2]), hu))
    frames.sort(key=lambda p: p[0])
    np.stack([f for _, f in frames]).astype("<i2").tofile(out_file)


def enhanced_ct(sources, out_file):
    """One Enhanced CT file from the native slices, frames stored top to bottom."""
    slices = sorted((pydicom.dcmread(s) for s in sources), key=lambda d: -float(d.ImagePositionPatient[2]))
    first = slices[0]
    ds = Dataset()
    for keyword in ["PatientName", "PatientID", "StudyInstanceUID", "StudyDate", "Modality",
                    "Manufacturer", "FrameOfReferenceUID", "PatientPosition", "Rows", "Columns",
                    "SamplesPerPixel", "PhotometricInterpretation", "BitsAllocated",
                    "BitsStored", "HighBit", "PixelRepresentation"]:
        setattr(ds, keyword, getattr(first, keyword))
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"
    ds.SOPInstanceUID = generate_uid(prefix=UID_ROOT)
    ds.SeriesInstanceUID = generate_uid(prefix=UID_ROOT)
    ds.SeriesNumber = 7
    ds.SeriesDescription = "enhanced CT (pydicom)"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]
    ds.NumberOfFrames = len(slices)
    measures = Dataset()
    measures.PixelSpacing = first.PixelSpacing
    measures.SliceThickness = first.SliceThickness
    transform = Dataset()
    transform.RescaleIntercept, transform.RescaleSlope, transform.RescaleType = 0, 1, "HU"
    shared = Dataset()
    shared.PixelMeasuresSequence = Sequence([measures])
    shared.PixelValueTransformationSequence = Sequence([transform])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    per_frame = []
    for s in slices:
        position, orientation, item = Dataset(), Dataset(), Dataset()
        position.ImagePositionPatient = s.ImagePositionPatient
        orientation.ImageOrientationPatient = s.ImageOrientationPatient
        item.PlanePositionSequence = Sequence([position])
        item.PlaneOrientationSequence = Sequence([orientation])
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(per_frame)
    ds.PixelData = b"".join(s.pixel_array.astype("<i2").tobytes() for s in slices)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.save_as(out_file, enforce_file_format=True)


def main():
    cip = Path(sys.argv[1])
    sources = [cip / s for s in SLICES]
    for old in ["native", "jpegls-lossless", "jpegls-near2", "jpeg12", "j2k-lossy"]:
        shutil.rmtree(HERE / old, ignore_errors=True)
    write_series(sources, HERE / "native", 2, "native (pydicom)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for folder, number, description, transform in [
            ("jls", 3, "JPEG-LS lossless (dcmcjpls)", None),
            ("jlsn", 4, "JPEG-LS near-lossless 2 (dcmcjpls)", to_12_bits),
            ("j12", 5, "JPEG extended 12-bit (dcmcjpeg)", to_12_bits),
            ("j2k", 6, "JPEG 2000 lossy (gdcmconv)", None),
        ]:
            write_series(sources, tmp / folder, number, description, transform)
        compress(tmp / "jls", HERE / "jpegls-lossless", "dcmcjpls", "+el")
        compress(tmp / "jlsn", HERE / "jpegls-near2", "dcmcjpls", "+en", "+md", "2")
        compress(tmp / "j12", HERE / "jpeg12", "dcmcjpeg", "+ee", "+q", "85")
        compress(tmp / "j2k", HERE / "j2k-lossy", "gdcmconv", "--j2k", "--lossy", "-q", "80")
    reference_hu(HERE / "jpeg12", ["dcmdjpeg"], HERE / "jpeg12.reference-hu.i16le")
    reference_hu(HERE / "j2k-lossy", ["gdcmconv", "--raw"], HERE / "j2k-lossy.reference-hu.i16le")
    enhanced_ct(sources, HERE / "enhanced-ct.dcm")
    run("dcmcjpls", "+el", HERE / "enhanced-ct.dcm", HERE / "enhanced-ct-jpegls.dcm")
    run("gdcmconv", "--j2k", HERE / "enhanced-ct.dcm", HERE / "enhanced-ct-j2k.dcm")


if __name__ == "__main__":
    main()
