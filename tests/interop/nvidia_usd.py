"""NVIDIA's usd-convert-gsplat, and OpenUSD's own ParticleField3DGaussianSplat schema (usd-core, in
that converter's environment):

python nvidia_usd.py convert in.ply|in.spz out.usda   (NVIDIA's command line, as
                                                       `python -m usd_convert_gsplat -i in -o out`)
python nvidia_usd.py read in.usda out.npz             (the schema reading a file: every splat prim's
                                                       attributes through its getters, the primvar
                                                       metadata, the local-to-world transform)
Several jobs run in one process when separated by "+".
"""

import contextlib
import io
import sys

import numpy as np
from pxr import Usd, UsdGeom, UsdVol
from usd_convert_gsplat import cli


def convert(source, out):
    sys.argv = ["usd_convert_gsplat", "-i", source, "-o", out]
    with contextlib.redirect_stdout(io.StringIO()):  # its progress lines
        cli.main()


def read(source, out):
    stage = Usd.Stage.Open(source)
    prims = [p for p in stage.Traverse() if p.IsA(UsdVol.ParticleField3DGaussianSplat)]
    assert len(prims) == 1, f"{len(prims)} splat prims"
    splat = UsdVol.ParticleField3DGaussianSplat(prims[0])
    time = Usd.TimeCode.Default()
    sh = splat.GetRadianceSphericalHarmonicsCoefficientsAttr()
    np.savez(
        out,
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


VERBS = {"convert": convert, "read": read}
args = sys.argv[1:]
while args:
    end = args.index("+") if "+" in args else len(args)
    verb, *rest = args[:end]
    args = args[end + 1 :]
    VERBS[verb](*rest)
