"""OpenUSD's own ParticleField3DGaussianSplat schema (usd-core, in NVIDIA's converter environment)
reading a file: every splat prim's attributes through the schema's getters, its primvar metadata,
and its local-to-world transform as OpenUSD computes it.

    python openusd_read.py in.usda out.npz
"""

import sys

import numpy as np
from pxr import Usd, UsdGeom, UsdVol

stage = Usd.Stage.Open(sys.argv[1])
prims = [p for p in stage.Traverse() if p.IsA(UsdVol.ParticleField3DGaussianSplat)]
assert len(prims) == 1, f"{len(prims)} splat prims"
splat = UsdVol.ParticleField3DGaussianSplat(prims[0])
time = Usd.TimeCode.Default()
sh = splat.GetRadianceSphericalHarmonicsCoefficientsAttr()
np.savez(
    sys.argv[2],
    positions=np.asarray(splat.GetPositionsAttr().Get()),
    orientations_xyzw=np.asarray(splat.GetOrientationsAttr().Get()),
    scales=np.asarray(splat.GetScalesAttr().Get()),
    opacities=np.asarray(splat.GetOpacitiesAttr().Get()),
    degree=splat.GetRadianceSphericalHarmonicsDegreeAttr().Get(),
    sh=np.asarray(sh.Get()),
    element_size=UsdGeom.Primvar(sh).GetElementSize(),
    interpolation=str(UsdGeom.Primvar(sh).GetInterpolation()),
    up_axis=str(UsdGeom.GetStageUpAxis(stage)),
    to_world=np.array(UsdGeom.Xformable(prims[0]).ComputeLocalToWorldTransform(time)).T,
)
