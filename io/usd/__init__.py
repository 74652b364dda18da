"""OpenUSD splats: `ParticleField3DGaussianSplat` prims in .usda, .usdc and .usdz files, with or
without OpenUSD's Python module (pxr; see stages.py).

Schema (pxr.UsdVol, usd-core >= 26.3): `positions` point3f[], `orientations` quatf[] (w first in
Gf.Quatf), `scales` float3[] LINEAR, `opacities` float[] LINEAR in [0,1],
`radiance:sphericalHarmonicsDegree` uniform int, `radiance:sphericalHarmonicsCoefficients` float3[]
with (d+1)^2 raw 3DGS coefficients per particle, particle-major (entry 0 = DC); each has a half
twin (`positionsh`, ...). We author `extent` ourselves: the box holding every splat out to the
radius where its alpha falls below 1/255, r = sqrt(2 ln(255 o)) sigma, the renderer's own rule.

Reading (`read`, `read_stage`, `read_frames`)
- Every ParticleField3DGaussianSplat prim (instance proxies included), plus UsdGeomPoints in the
  layout Adobe's USD file-format plugins write for splats, recognised by `primvars:rot`,
  `primvars:widths1` and `primvars:widths2`: `points`; `widths`/`primvars:widths1`/`widths2` are
  2 sigma per axis; `primvars:rot` quatf; `primvars:displayOpacity` linear; `primvars:displayColor`
  the DC colour clamped to [0,1]; `primvars:fRest0..` channel-major like PLY's f_rest; and
  UsdGeomPoints as Blender's USD export writes splat point clouds, recognised by `primvars:rotation`
  and `primvars:scale` (see dialects._blender_cloud). Other prims are skipped with a SplatFileWarning
  listing them.
- Float attributes are preferred to their half twins, as the schema asks. Per the schema, an array
  too long is truncated to the particle count and one too short is ignored (orientation identity,
  scale 1, opacity 1, SH a grey DC); each such repair is reported in a warning.
- Each prim's local-to-world transform is applied, then the stage's upAxis and metersPerUnit, then
  the flip from USD's Y-up (RUB) to the model's 3DGS axes (RDF: y down, z forward), so clouds come
  out in the model's axes and metres. axes="RUB" keeps Y-up, axes=None the stage's own axes;
  meters_per_unit=None keeps its units. USD's fallbacks apply to unauthored metadata: Y up, 0.01 m
  per unit (a warning says so). Our files' prims carry UPRIGHT_OP, so this gives their values back.
- A ParticleField3DGaussianSplat without UPRIGHT_OP (NVIDIA's and OpenUSD's converters copy the PLY's
  coordinates into a Y-up stage unchanged: shown as stored, the capture is upside down) is, with
  unmarked="capture" (the default), taken as capture coordinates: units apply, no axis change, so
  the PLY's values come back. unmarked="stage" reads it in the stage's axes like any geometry.
  A transform that is not a rotation times a uniform scale is exact for positions and covariances
  (re-diagonalised into rotation and scales) but not for SH colours; its anisotropy is reported.
- Our own files also carry `splatwright:opacityLogits`, `splatwright:logScales` and
  `splatwright:rotations` (float32 as the model stores them), used when they still agree with
  `opacities`/`scales`/`orientations`, so PLY -> USD -> PLY is exact; and a cloud read from USD and
  written back unchanged reproduces the file's linear values. `splatwright:antialiased` (true)
  marks splats made for antialiased rendering (SplatCloud.antialiased).

Writing (`write`, `write_stage`, `write_frames`): a Y-up, metersPerUnit 1 stage holding the values
as the reference converters (OpenUSD's hdParticleField example, NVIDIA's usd-convert-gsplat) write
them: the capture's PLY coordinates, normalised quaternions, SH with primvar metadata (elementSize
(d+1)^2, vertex interpolation); the prim's UPRIGHT_OP, a half turn about X, stands the y-down
capture upright in the stage (layout="upright"). layout="y-up" turns the values themselves instead
(no transform), layout="as-is" writes neither (as NVIDIA's converter). One prim per cloud (default
/Splats); a sequence of same-count clouds (any iterable, consumed one at a time) becomes time
samples on one prim, where an attribute that never changes is authored once as its default value.
half=True stores orientations, scales, opacities and SH as half floats (about half the size;
positions stay float32 unless half_positions=True). Extras become `primvars:<name>` with vertex
interpolation. Without pxr.UsdVol's schema classes (an older pxr, e.g. one bundled with Blender)
the same prim and attributes are authored by name through the generic API, giving the same file.

Modules, each importing only those above it in this list:
- schema: prim type and attribute names, value types, and the conversions between a cloud's arrays
  and a prim's values (_frame_values, _Samples, the exact-value preferences, alpha_extent, data_size)
- crate: crate (.usdc) files checked against their own sizes (with its own LZ4 block decoder)
- usdz: the .usdz package of one layer
- usda, usda_parse: OpenUSD text layers without OpenUSD (the layer model and its text; the parser)
- pxr_stages, text_stages: the two implementations of the stage interface
- stages: the stage interface, and the one place that asks whether pxr exists (`stages.active`)
- dialects: the splat dialects read from prims (the schema's, Adobe's and Blender's)
- reader, writer: the public reading and writing below
"""

from . import stages
from .reader import AXES, MAGIC, SplatPrim, read, read_frames, read_stage, stage_matrix, time_codes
from .schema import (
    ADOBE_PRIMVARS,
    ANISOTROPY_TOLERANCE,
    ANTIALIASED,
    BLENDER_BASE,
    BLENDER_PRIMVARS,
    CUSTOM,
    DTYPE_KEY,
    EXTRA_TYPES,
    LAYOUTS,
    LOG_SCALES,
    LOGITS,
    RAW_ROTATIONS,
    REST_COUNTS,
    SCHEMA,
    SH_COEFFS,
    SH_DEGREE,
    TYPE_NAME,
    UNMARKED,
    UPRIGHT,
    UPRIGHT_OP,
    alpha_extent,
    data_size,
)
from .writer import write, write_frames, write_stage

__all__ = [
    "ADOBE_PRIMVARS",
    "ANISOTROPY_TOLERANCE",
    "ANTIALIASED",
    "AXES",
    "BLENDER_BASE",
    "BLENDER_PRIMVARS",
    "CUSTOM",
    "DTYPE_KEY",
    "EXTRA_TYPES",
    "LAYOUTS",
    "LOG_SCALES",
    "LOGITS",
    "MAGIC",
    "RAW_ROTATIONS",
    "REST_COUNTS",
    "SCHEMA",
    "SH_COEFFS",
    "SH_DEGREE",
    "TYPE_NAME",
    "UNMARKED",
    "UPRIGHT",
    "UPRIGHT_OP",
    "SplatPrim",
    "alpha_extent",
    "data_size",
    "read",
    "read_frames",
    "read_stage",
    "stage_matrix",
    "stages",
    "time_codes",
    "write",
    "write_frames",
    "write_stage",
]
