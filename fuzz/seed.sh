#!/usr/bin/env bash
# Builds each fuzz target's seed corpus in fuzz/corpus/<target>/ (git-ignored) from the shared
# third-party data (../shared/data or $LUNGMOTION_SHARED_DATA) and sample-volumes/.
#
# Seeds are kept small (a few kB: libFuzzer mutates faster and its default -max_len follows the
# largest seed), so the CTs are cut down to 16 × 16 pixels by pydicom/numpy, and re-encoded by
# GDCM (RLE, JPEG, JPEG-LS, JPEG 2000) when gdcmconv is installed. A missing tool only means
# fewer seeds: every step that needs one is skipped with a note.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(dirname "$here")"
shared="${LUNGMOTION_SHARED_DATA:-$(dirname "$repo")/shared/data}"
corpus="$here/corpus"
mkdir -p "$corpus"/{dicom_series,nifti,nrrd,metaimage,trace_csv,trace_json,zip}

have() { command -v "$1" >/dev/null 2>&1; }
note() { echo "seed.sh: $*" >&2; }

cip="$shared/cip-chest-ct64"
if [[ ! -d "$cip" ]]; then
    note "no shared data at $shared: seeding from sample-volumes/ and generated files only"
fi

# --- DICOM: whole small slices as they come, then cut-down and re-encoded copies -----------
for f in "$cip/dicom/IMG0001.dcm" "$cip/dicom/IMG0040.dcm" "$repo/sample-volumes/phantom-dicom/IMG0001.dcm"; do
    [[ -f "$f" ]] && install -m 0644 "$f" "$corpus/dicom_series/$(basename "$(dirname "$(dirname "$f")")")-$(basename "$f")"
done

if python3 -c 'import pydicom, numpy' 2>/dev/null; then
    src="$cip/dicom/IMG0040.dcm"
    [[ -f "$src" ]] || src="$repo/sample-volumes/phantom-dicom/IMG0001.dcm"
    python3 - "$src" "$corpus" <<'PY'
import sys, gzip, json, struct, zipfile, io
import numpy as np
import pydicom
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

src, corpus = sys.argv[1], sys.argv[2]
ds = pydicom.dcmread(src)
px = ds.pixel_array[24:40, 24:40].astype(np.int16)

def crop(ds, syntax, name):
    d = ds.copy()
    d.Rows, d.Columns = px.shape
    d.PixelData = px.astype("<i2").tobytes()
    d.file_meta.TransferSyntaxUID = syntax
    d.save_as(f"{corpus}/dicom_series/{name}", enforce_file_format=True,
              little_endian=True, implicit_vr=(syntax == ImplicitVRLittleEndian))

crop(ds, ImplicitVRLittleEndian, "crop16-implicit.dcm")
crop(ds, ExplicitVRLittleEndian, "crop16-explicit.dcm")

# NIfTI-1 (raw and gzip) and NIfTI-2 of a 16 x 16 x 4 block of that crop, RAS with sform.
vol = np.stack([px] * 4, axis=-1)  # i, j, k

def nifti1(data, dtype_code, bitpix):
    h = bytearray(348)
    struct.pack_into("<i", h, 0, 348)
    dims = [3, *data.shape, 1, 1, 1, 1]
    struct.pack_into("<8h", h, 40, *dims)
    struct.pack_into("<hh", h, 70, dtype_code, bitpix)
    struct.pack_into("<8f", h, 76, 1, 4.17, 4.17, 3.99, 0, 0, 0, 0)
    struct.pack_into("<f", h, 108, 352)  # vox_offset
    struct.pack_into("<ff", h, 112, 1, 0)  # scl_slope, scl_inter
    struct.pack_into("<hh", h, 252, 1, 1)  # qform_code, sform_code
    struct.pack_into("<4f", h, 280, -4.17, 0, 0, 128.4)
    struct.pack_into("<4f", h, 296, 0, -4.17, 0, 264.4)
    struct.pack_into("<4f", h, 312, 0, 0, 3.99, -360.3)
    h[344:348] = b"n+1\0"
    return bytes(h) + b"\0" * 4 + data.astype("<i2").tobytes(order="F")

def nifti2(data):
    h = bytearray(540)
    struct.pack_into("<i", h, 0, 540)
    h[4:12] = b"n+2\0\r\n\x1a\n"
    struct.pack_into("<hh", h, 12, 4, 16)  # datatype int16, bitpix
    struct.pack_into("<8q", h, 16, 3, *data.shape, 1, 1, 1, 1)
    struct.pack_into("<8d", h, 104, 1, 4.17, 4.17, 3.99, 0, 0, 0, 0)
    struct.pack_into("<q", h, 168, 544)  # vox_offset
    struct.pack_into("<dd", h, 176, 1, 0)
    struct.pack_into("<ii", h, 344, 0, 1)  # qform_code, sform_code
    struct.pack_into("<4d", h, 400, -4.17, 0, 0, 128.4)
    struct.pack_into("<4d", h, 432, 0, -4.17, 0, 264.4)
    struct.pack_into("<4d", h, 464, 0, 0, 3.99, -360.3)
    return bytes(h) + b"\0" * 4 + data.astype("<i2").tobytes(order="F")

n1 = nifti1(vol, 4, 16)
open(f"{corpus}/nifti/crop16.nii", "wb").write(n1)
open(f"{corpus}/nifti/crop16.nii.gz", "wb").write(gzip.compress(n1, mtime=0))
open(f"{corpus}/nifti/crop16-nifti2.nii", "wb").write(nifti2(vol))
labels = (vol < -400).astype(np.int16)
open(f"{corpus}/nifti/labels16.nii", "wb").write(nifti1(labels, 4, 16))

# NRRD: the same block raw, gzip, and big-endian.
def nrrd(encoding, endian, payload):
    head = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
            "sizes: 16 16 4\nspace directions: (4.17,0,0) (0,4.17,0) (0,0,3.99)\n"
            "kinds: domain domain domain\n"
            f"endian: {endian}\nencoding: {encoding}\nspace origin: (-128.4,-264.4,-360.3)\n\n")
    return head.encode() + payload

le = vol.astype("<i2").tobytes(order="F")
open(f"{corpus}/nrrd/crop16-raw.nrrd", "wb").write(nrrd("raw", "little", le))
open(f"{corpus}/nrrd/crop16-gzip.nrrd", "wb").write(nrrd("gzip", "little", gzip.compress(le, mtime=0)))
open(f"{corpus}/nrrd/crop16-big.nrrd", "wb").write(nrrd("raw", "big", vol.astype(">i2").tobytes(order="F")))

# MetaImage, as lungmotion writes it: scalar and a 3-channel field.
def mha(channels):
    head = ("ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
            "CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
            "Offset = -128.4 -264.4 -360.3\nCenterOfRotation = 0 0 0\nAnatomicalOrientation = RAI\n"
            "ElementSpacing = 4.17 4.17 3.99\nDimSize = 16 16 4\n"
            + (f"ElementNumberOfChannels = {channels}\n" if channels > 1 else "")
            + "ElementType = MET_FLOAT\nElementDataFile = LOCAL\n")
    data = np.repeat(vol.astype("<f4").ravel(order="F"), channels).tobytes()
    return head.encode() + data
open(f"{corpus}/metaimage/crop16.mha", "wb").write(mha(1))
open(f"{corpus}/metaimage/field16.mha", "wb").write(mha(3))

# Zip: a small series (stored and deflated), a folder entry and a DICOMDIR name.
slices = [open(f"{corpus}/dicom_series/{n}", "rb").read()
          for n in ("crop16-implicit.dcm", "crop16-explicit.dcm")]
for method, name in ((zipfile.ZIP_STORED, "series-stored.zip"), (zipfile.ZIP_DEFLATED, "series-deflated.zip")):
    with zipfile.ZipFile(f"{corpus}/zip/{name}", "w", method) as z:
        z.writestr("export/", b"")
        for i, s in enumerate(slices):
            z.writestr(f"export/IM{i:04}", s)
        z.writestr("DICOMDIR", b"\0" * 132)
with zipfile.ZipFile(f"{corpus}/zip/empty.zip", "w") as z:
    pass
PY
else
    note "python3 with pydicom and numpy not found: no cut-down DICOM, NIfTI, NRRD, MetaImage or zip seeds"
fi

if have gdcmconv && [[ -f "$corpus/dicom_series/crop16-explicit.dcm" ]]; then
    for codec in rle jpeg jpegls j2k deflated; do
        gdcmconv --"$codec" "$corpus/dicom_series/crop16-explicit.dcm" \
            "$corpus/dicom_series/crop16-$codec.dcm" 2>/dev/null || note "gdcmconv --$codec failed"
    done
else
    note "gdcmconv (apt-get install -y libgdcm-tools) not found: no compressed DICOM seeds"
fi

if have dcmconv && [[ -f "$corpus/dicom_series/crop16-explicit.dcm" ]]; then
    dcmconv +tb "$corpus/dicom_series/crop16-explicit.dcm" "$corpus/dicom_series/crop16-bigendian.dcm" ||
        note "dcmconv +tb failed"
else
    note "dcmconv (apt-get install -y dcmtk) not found: no big-endian DICOM seed"
fi

# Small whole files of the shared data and the phantom.
for f in "$cip/wholeLung-64.nrrd" "$cip/lm-64.nrrd"; do
    [[ -f "$f" ]] && install -m 0644 "$f" "$corpus/nrrd/"
done
install -m 0644 "$repo/sample-volumes/phantom-truth.nii.gz" "$corpus/nifti/"

# --- Traces: the MIMIC respiration waveform cut to 20 s, in the forms the reader accepts ---
resp="$shared/respiration-mimic/03700181_RESP.csv"
if [[ -f "$resp" ]]; then
    head -n 2501 "$resp" | head -c 60000 > "$corpus/trace_csv/mimic-raw-head.csv"
    # Scaled to millilitres (≈ 500 mL breaths) so the seed is accepted and reaches the checks.
    awk -F, 'NR == 1 { print "time_s,volume_ml"; next } NR <= 501 { printf "%s,%.3f\n", $1, $2 * 400 }' \
        "$resp" > "$corpus/trace_csv/mimic-ml.csv"
    awk -F, 'NR == 1 { print "# MIMIC 03700181\ntime_ms,volume_l"; next } NR <= 201 { printf "%d,%.5f\n", $1 * 1000, $2 * 0.4 }' \
        "$resp" > "$corpus/trace_csv/mimic-ms-l.csv"
    awk -F, 'NR == 1 { next } NR <= 201 { t = t sep $1; v = v sep sprintf("%.3f", $2 * 400); sep = ", " }
        END { printf "{\"time_s\": [%s], \"volume_ml\": [%s]}\n", t, v }' "$resp" > "$corpus/trace_json/mimic-ml.json"
else
    note "no $resp: traces from generated curves only"
fi
printf 'time_s,volume_ml\n0,0\n1,250\n2,500\n3,250\n4,0\n' > "$corpus/trace_csv/breath.csv"
printf '\xef\xbb\xbftime_ms,volume_l\r\n0,0\r\n2000,0.5\r\n4000,0\r\n' > "$corpus/trace_csv/bom-crlf.csv"
printf '{"time_s": [0, 1, 2, 3, 4], "volume_ml": [0, 250, 500, 250, 0]}\n' > "$corpus/trace_json/breath.json"
printf '{"time_ms": [0, 2000, 4000], "volume_l": [0, 0.5, 0]}\n' > "$corpus/trace_json/ms-l.json"

for t in "$corpus"/*/; do
    printf '%-14s %3d seeds, %7d bytes\n' "$(basename "$t")" "$(find "$t" -type f | wc -l)" \
        "$(find "$t" -type f -printf '%s\n' | awk '{ s += $1 } END { print s + 0 }')"
done
