"""The README's virtual 4D-CT figure: a coronal slice through the phantom's tumour of the
planning CT, the demo's end-inhale virtual CT phase (frame 0) and their difference.

Reads what `lungmotion demo` wrote with an independent reader (SimpleITK), so the figure
shows the files a planning system would load. Usage:
    python3 docs/virtual_ct_figure.py sample-volumes/phantom-dicom demo-out docs/virtual-ct-phase.png
"""
import sys

import numpy as np
import SimpleITK as sitk

ct_dir, run_dir, out = sys.argv[1:4]
reader = sitk.ImageSeriesReader()
reader.SetFileNames(reader.GetGDCMSeriesFileNames(ct_dir))
ct = reader.Execute()
phase = sitk.ReadImage(f"{run_dir}/frames/0/virtual-ct.nii.gz")
# The phase on the CT's grid (same grid by construction; resampling guards any LPS/RAS slip).
phase = sitk.Resample(phase, ct, sitk.Transform(), sitk.sitkLinear, -1000.0, sitk.sitkFloat32)
tumour_lps = (-95.0, 20.0, -80.0)
_, j, _ = ct.TransformPhysicalPointToIndex(tumour_lps)
a = sitk.GetArrayFromImage(ct).astype(np.float32)[:, j, :]      # rows z, columns x
b = sitk.GetArrayFromImage(phase)[:, j, :]
sx, _, sz = ct.GetSpacing()
repeat = max(1, int(round(sz / sx)))


def window(img, lo=-1000.0, hi=200.0):
    return (np.clip((img - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8)


diff = np.clip(128 + (b - a) / 4.0, 0, 255).astype(np.uint8)   # ±512 HU → black…white
gap = np.full((a.shape[0], 1), 255, np.uint8)
panel = np.hstack([window(a), gap, window(b), gap, diff])
panel = np.repeat(panel[::-1], repeat, axis=0)                 # superior at the top
panel = np.kron(panel, np.ones((4, 4), np.uint8))              # 5 mm voxels: enlarged 4×
sitk.WriteImage(sitk.GetImageFromArray(panel), out)
print(f"coronal slice j={j} (y={tumour_lps[1]} mm LPS), {panel.shape[1]}x{panel.shape[0]} px -> {out}")
