"""What an export writes beyond the splats themselves: SH degree (reduced on export), SPZ version and
axes, half floats for OpenUSD and pruning of faint splats. The export and animation export operators take
them as properties (unset ones come from the preferences), the command verb as flags."""

from dataclasses import dataclass

import bpy
from bpy.props import EnumProperty, FloatProperty
from bpy_extras.io_utils import ExportHelper

from ...core import economy
from ...core import sh as shmod
from ...io import format_of
from ..ui import preferences

SPZ_VERSION_OF_DEGREE_4 = 4  # SPZ versions before 4 hold SH up to degree 3


@dataclass(frozen=True)
class ExportOptions:
    sh_degree: int = None  # None: as the splats have it; otherwise reduced to at most this
    spz_version: int = 3
    half: bool = False  # OpenUSD half floats
    prune_opacity: float = 0.0  # splats whose opacity is below this are left out (0: none)
    spz_axes: str = "rub"  # the axes an SPZ stores: SPZ's documented RUB, or PLY's RDF

    def __post_init__(self):
        if self.sh_degree is not None and self.sh_degree not in range(shmod.MAX_DEGREE + 1):
            raise ValueError(f"SH degree must be 0..{shmod.MAX_DEGREE}, got {self.sh_degree}")
        if self.spz_version not in (2, 3, 4):
            raise ValueError(f"SPZ version must be 2, 3 or 4, got {self.spz_version}")
        if self.spz_axes not in ("rub", "rdf"):
            raise ValueError(f"SPZ axes must be rub or rdf, got {self.spz_axes}")
        if not 0.0 <= self.prune_opacity <= 1.0:
            raise ValueError(f"the opacity to prune below must be in [0, 1], got {self.prune_opacity}")

    def kept(self, cloud):
        """The boolean mask of the splats pruning keeps (None: all)."""
        return economy.opacity_mask(cloud, self.prune_opacity) if self.prune_opacity > 0 else None

    def reduce(self, cloud, kept=None):
        """The cloud as written: pruned (by `kept`, or by its own opacities) and its SH reduced."""
        kept = self.kept(cloud) if kept is None else kept
        if kept is not None:
            cloud = cloud[kept]
        if self.sh_degree is not None and self.sh_degree < cloud.sh_degree:
            cloud = cloud.with_sh_degree(self.sh_degree)
        return cloud

    def writer_options(self, path, cloud=None):
        """Keyword arguments for write_splats of `cloud` to `path`: the options its format takes. SPZ
        Version is the lowest version written: degree 4, which only v4 holds, is written as v4 (an SH
        Degree of 3 keeps older readers' versions)."""
        fmt = format_of(path)
        if fmt == "spz":
            return {
                "version": max(self.spz_version, SPZ_VERSION_OF_DEGREE_4)
                if cloud is not None and cloud.sh_degree == 4
                else self.spz_version,
                "spz_axes": self.spz_axes,
            }
        if fmt == "usd":
            return {"half": self.half}
        return {}


def from_settings(sh_degree="KEEP", spz_version="3", use_half=False, prune_opacity=0.0, spz_axes="RUB"):
    """ExportOptions from the property values (enum identifiers as the properties hold them)."""
    return ExportOptions(
        None if sh_degree == "KEEP" else int(sh_degree),
        int(spz_version),
        bool(use_half),
        float(prune_opacity),
        spz_axes.lower(),
    )


PREFERRED = ("sh_degree", "spz_version", "use_half")  # unset in an operator call: the preferences'


class ExportOptionProperties:
    """The options as operator properties (a mixin for ExportHelper operators). Properties not given
    to the operator take the preferences' values, in the dialog and from Python alike."""

    sh_degree: preferences.sh_degree_property()
    spz_version: preferences.spz_version_property()
    use_half: preferences.half_property()
    prune_opacity: FloatProperty(
        name="Prune Opacity Below",
        default=0.0,
        min=0.0,
        max=1.0,
        description="Leave out splats fainter than this (0 keeps every splat)",
    )
    spz_axes: EnumProperty(
        name="SPZ Axes",
        items=(
            ("RUB", "RUB", "SPZ's documented axes (x right, y up, z back), as Niantic's library and Blender read SPZ"),
            ("RDF", "RDF", "PLY's axes (x right, y down, z front), as splat-transform reads SPZ"),
        ),
        default="RUB",
        description="The axes an SPZ file stores (.spz files only); v4 files name them in a record",
    )

    def export_options(self, context):
        prefs = preferences.current(context)
        values = {name: getattr(self if self.properties.is_property_set(name) else prefs, name) for name in PREFERRED}
        return from_settings(**values, prune_opacity=self.prune_opacity, spz_axes=self.spz_axes)

    def invoke(self, context, event):
        """The dialog opens on the preferences' options and format."""
        prefs = preferences.current(context)
        for name in PREFERRED:
            if not self.properties.is_property_set(name):
                setattr(self, name, getattr(prefs, name))
        if not self.filepath:
            stem = bpy.path.display_name_from_filepath(bpy.data.filepath) or "untitled"
            self.filepath = stem + preferences.default_extension(context)
        return ExportHelper.invoke(self, context, event)
