#!/usr/bin/env python3
"""Writes tests/data/dicom/un-vr/: the first 3 slices of the CIP series (shared data,
cip-chest-ct64/dicom) with every data element's VR written as UN, Explicit VR Little
Endian, as some PACS and toolkits re-encode series.

Tool: pydicom 3.0.2 (pip install pydicom==3.0.2), Python 3.11. Each element's value is
encoded by pydicom in Implicit VR Little Endian (PS3.5 6.2.2: a UN value is the implicit
encoding, sequences included) and written under an explicit header with VR "UN" and the
same length (defined, or undefined for sequences). One sequence, ProcedureCodeSequence
(0008,1032) with one coded item, is added so that a UN sequence of undefined length is
covered. The script reads every file back with pydicom (UN replaced by the dictionary's VR)
and checks the values equal the original's, and checks every top-level VR is "UN".

Usage: python3 make_un_vr.py <cip dicom dir> <output dir>
"""
import io
import struct
import sys
from pathlib import Path

import pydicom
from pydicom.dataset import Dataset
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_data_element, write_file_meta_info
from pydicom.sequence import Sequence

assert pydicom.__version__ == "3.0.2", pydicom.__version__
EXPLICIT_LE = "1.2.840.10008.1.2.1"


def implicit_encoding(elem):
    """(length field, value bytes) of `elem` as pydicom writes it in Implicit VR LE."""
    fp = DicomBytesIO()
    fp.is_little_endian = True
    fp.is_implicit_VR = True
    write_data_element(fp, elem)
    raw = fp.getvalue()
    (length,) = struct.unpack_from("<I", raw, 4)
    return length, raw[8:]


def with_procedure_code(ds):
    code = Dataset()
    code.CodeValue = "CTCHEST"
    code.CodingSchemeDesignator = "99LOCAL"
    code.CodeMeaning = "CT chest"
    ds.ProcedureCodeSequence = Sequence([code])
    ds["ProcedureCodeSequence"].is_undefined_length = True
    return ds


def write_un(ds, path):
    meta = ds.file_meta
    meta.TransferSyntaxUID = EXPLICIT_LE
    out = io.BytesIO()
    out.write(b"\0" * 128 + b"DICM")
    write_file_meta_info(out, meta, enforce_standard=True)
    for elem in ds:
        length, value = implicit_encoding(elem)
        out.write(struct.pack("<HH2sHI", elem.tag.group, elem.tag.element, b"UN", 0, length))
        out.write(value)
    path.write_bytes(out.getvalue())


def top_level_vrs(path):
    """The VR bytes of every top-level element, read straight from the file."""
    raw = Path(path).read_bytes()
    (meta_len,) = struct.unpack_from("<I", raw, 140)
    pos, vrs = 144 + meta_len, set()
    while pos < len(raw):
        vr = raw[pos + 4 : pos + 6]
        (length,) = struct.unpack_from("<I", raw, pos + 8)
        vrs.add(vr)
        if length == 0xFFFFFFFF:  # a sequence: skip to its delimiter
            pos = raw.index(b"\xfe\xff\xdd\xe0\x00\x00\x00\x00", pos) + 8
        else:
            pos += 12 + length
    return vrs


def main(source, target):
    target.mkdir(parents=True, exist_ok=True)
    for name in ["IMG0001.dcm", "IMG0002.dcm", "IMG0003.dcm"]:
        original = with_procedure_code(pydicom.dcmread(source / name))
        write_un(original, target / name)
        assert top_level_vrs(target / name) == {b"UN"}, top_level_vrs(target / name)
        pydicom.config.replace_un_with_known_vr = True
        back = pydicom.dcmread(target / name)
        for elem in original:
            assert back[elem.tag].value == elem.value, (name, elem.tag)
        assert back.ProcedureCodeSequence[0].CodeMeaning == "CT chest"
        print(f"{target / name}: {(target / name).stat().st_size} bytes")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
