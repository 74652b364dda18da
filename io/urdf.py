"""URDF robot descriptions: links, joints (origins, axes, limits, mimics) and visuals.

`read_urdf(path)` gives the core.kinematics.KinematicTree: links in topological order, each with
the URDF joint that has it as its child. `read_description(path, package_paths)` adds each link's
visuals (origin, box / cylinder / sphere / mesh file with its scale, material colour) with their
files resolved, and `read_robot(path, ...)` turns all of it into a core.robot.SplatRobot: the
visuals' meshes converted to splats, bound rigidly to their links.

Mesh files follow io.policy's reading rule: they are read only from the allowed roots, the URDF's
folder and the package paths the user gives (`package_paths`, then the ROS_PACKAGE_PATH
environment variable, which the user set too), once `..` and symbolic links are followed; absolute
paths, `../` escapes and special files are refused with the same error as a missing file, unless
`allow_outside=True`. `package://name/rest` is looked up in those roots: as `<root>/name/rest`, or
`<root>/rest` for a root itself called `name`, or the bare `rest` relative to the URDF (what
pybullet does for its data); with allow_outside the URDF's parent folders are searched too.
`file://` paths (percent escapes decoded) and plain relative paths are taken from the URDF's
folder. Meshes are read by io.meshes (OBJ natively, STL and DAE through trimesh), whose own
textures follow the same rule inside the mesh's folder.

Lenient where the common loaders (pybullet, yourdfpy, Pinocchio) are and it is harmless: text
before `<?xml` that is only whitespace, limits given upper-first (swapped, with a warning), a
missing <limit> on a revolute or prismatic joint (no limits, with a warning), and the joint type
"spherical" (a ball joint). Anything else malformed raises SplatFileError naming the file, the
element and the problem.
"""

import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..core import color
from ..core.kinematics import KinematicsError, KinematicTree, rpy_matrices, transforms
from .common import SplatFileError, SplatFileWarning, check_file, read_text
from .policy import referenced_file

_TYPES = ("fixed", "revolute", "continuous", "prismatic", "floating", "planar", "spherical")


@dataclass
class Visual:
    """One <visual> of a link. origin: (4,4) in the link's frame. geometry: 'box' (size = x, y, z),
    'cylinder' (radius, length, along z), 'sphere' (radius,) or 'mesh' (path, scale). rgba: the
    material colour as written (display sRGB, as URDF viewers show it), or None."""

    link: str
    origin: np.ndarray
    geometry: str
    size: tuple = ()
    path: Path = None
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    rgba: tuple = None
    name: str = ""

    @property
    def linear_color(self):
        return None if self.rgba is None else tuple(color.srgb_to_linear(np.clip(self.rgba[:3], 0.0, 1.0)))


@dataclass
class RobotDescription:
    """A URDF: its name, kinematic tree and visuals (in file order)."""

    name: str
    tree: KinematicTree
    visuals: list


def read_urdf(path):
    """Read a .urdf file into a KinematicTree; SplatFileError names the file and the problem."""
    path = Path(path)
    check_file(path)
    return parse_urdf(read_text(path), source=str(path))


def parse_urdf(text, source="<string>"):
    """Parse URDF XML text into a KinematicTree (`source` names it in error messages)."""
    robot = _root(text, source)
    links, joints = _links_and_joints(robot, source)
    return _tree(links, joints, source)


def read_description(path, package_paths=(), allow_outside=False):
    """Read a .urdf file with its visuals (mesh paths resolved, not yet read) into a RobotDescription.
    allow_outside: follow mesh names outside the allowed roots too (see the module notes)."""
    path = Path(path)
    check_file(path)
    source = str(path)
    robot = _root(read_text(path), source)
    links, joints = _links_and_joints(robot, source)
    tree = _tree(links, joints, source)
    resolver = _Resolver(path, package_paths, allow_outside)
    materials = _materials(robot, source)
    visuals = [v for link in robot.findall("link") for v in _visuals(source, link, materials, resolver)]
    return RobotDescription(robot.get("name", path.stem), tree, visuals)


def read_robot(
    path,
    package_paths=(),
    max_splats=None,
    target_psnr=None,
    progress=None,
    info=None,
    allow_outside=False,
    **style,
):
    """A URDF as a core.robot.SplatRobot: every visual meshed (primitives tessellated, mesh files
    read and scaled), placed by its origin on its link at the zero configuration, and converted to
    splats in one pass (one density over the whole robot: `max_splats` or `target_psnr` as in
    core.mesh_to_splats.mesh_to_splats; the default is a budget of DEFAULT_SPLATS). allow_outside:
    follow mesh and texture names outside the allowed folders too (see the module notes)."""
    from ..core.robot import DEFAULT_SPLATS, splat_robot, visual_mesh
    from .meshes import has_own_colours, read_mesh_file

    description = read_description(path, package_paths, allow_outside)
    if not description.visuals:
        raise SplatFileError(path, "no <visual> elements: nothing to make splats from")
    index = {name: i for i, name in enumerate(description.tree.names)}
    files, parts = {}, []
    for visual in description.visuals:
        mesh = None
        if visual.geometry == "mesh":
            if visual.path not in files:
                files[visual.path] = read_mesh_file(visual.path, allow_outside=allow_outside)
            mesh = files[visual.path]
            colour = None if has_own_colours(mesh) else visual.linear_color
        else:
            colour = visual.linear_color
        parts.append(
            (index[visual.link], visual_mesh(visual.geometry, visual.size, mesh, visual.scale, colour), visual.origin)
        )
    if max_splats is None and target_psnr is None:
        max_splats = DEFAULT_SPLATS
    try:
        return splat_robot(
            description.tree,
            parts,
            max_splats=max_splats,
            target_psnr=target_psnr,
            progress=progress,
            info=info,
            name=description.name,
            **style,
        )
    except ValueError as exc:
        raise SplatFileError(path, str(exc)) from None


# parsing -----------------------------------------------------------------------------------------


def _root(text, source):
    text = text.lstrip("\ufeff \t\r\n")  # a BOM or blank lines before <?xml: harmless
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as exc:
        raise SplatFileError(source, f"not valid XML: {exc}") from None
    if robot.tag != "robot":
        raise SplatFileError(source, f"root element is <{robot.tag}>, expected <robot>")
    return robot


def _links_and_joints(robot, source):
    links = [_attr(source, link, "name", "link") for link in robot.findall("link")]
    if not links:
        raise SplatFileError(source, "no <link> elements")
    declared = set(links)
    if len(declared) != len(links):
        raise SplatFileError(source, "link names are not unique")
    joints = [_joint(source, j, declared) for j in robot.findall("joint")]
    if joints:  # every origin in one batch: per-joint NumPy calls add up
        poses = np.array([j["origin"] for j in joints])
        for j, m in zip(joints, transforms(rpy_matrices(poses[:, 1]), poses[:, 0])):
            j["origin"] = m
    if len({j["name"] for j in joints}) != len(joints):
        raise SplatFileError(source, "joint names are not unique")
    return links, joints


def _tree(links, joints, source):
    children = {j["child"] for j in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise SplatFileError(
            source, f"expected exactly one root link (a link that is no joint's child), found {roots or 'none'}"
        )
    try:
        tree = KinematicTree.from_joints(joints, root=roots[0])
    except KinematicsError as exc:
        raise SplatFileError(source, str(exc)) from None
    lonely = set(links) - set(tree.names)
    if lonely:
        raise SplatFileError(source, f"links {sorted(lonely)} are not connected to root '{roots[0]}'")
    return tree


def _attr(source, element, key, what):
    value = element.get(key)
    if value is None:
        raise SplatFileError(source, f"<{what}> without a '{key}' attribute")
    return value


def _numbers(source, text, count, where):
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise SplatFileError(source, f"{where}: '{text}' is not {count} numbers") from None
    if values.shape != (count,) or not np.isfinite(values).all():
        raise SplatFileError(source, f"{where}: '{text}' is not {count} finite numbers")
    return values


def _origin(source, element, where):
    """The (4,4) transform of an element's <origin> (identity without one)."""
    xyz, rpy = _pose(source, element, where)
    return transforms(rpy_matrices(rpy), xyz)


def _pose(source, element, where):
    """The xyz and rpy of an element's <origin> (zeros without one)."""
    origin = element.find("origin")
    if origin is None:
        return np.zeros(3), np.zeros(3)
    return (
        _numbers(source, origin.get("xyz", "0 0 0"), 3, f"{where} origin xyz"),
        _numbers(source, origin.get("rpy", "0 0 0"), 3, f"{where} origin rpy"),
    )


def _joint(source, element, links):
    name = _attr(source, element, "name", "joint")
    where = f"joint '{name}'"
    kind = _attr(source, element, "type", "joint")
    if kind not in _TYPES:
        raise SplatFileError(source, f"{where} has type '{kind}'; supported: {', '.join(_TYPES)}")
    ends = {}
    for end in ("parent", "child"):
        tag = element.find(end)
        if tag is None or tag.get("link") is None:
            raise SplatFileError(source, f"{where} has no <{end} link=...>")
        if tag.get("link") not in links:
            raise SplatFileError(source, f"{where}: {end} link '{tag.get('link')}' is not declared")
        ends[end] = tag.get("link")
    axis_tag = element.find("axis")
    axis = (
        _numbers(source, axis_tag.get("xyz", "1 0 0"), 3, f"{where} axis")
        if axis_tag is not None
        else np.array([1.0, 0.0, 0.0])
    )
    if kind in ("revolute", "continuous", "prismatic", "planar") and not 1e-12 <= np.linalg.norm(axis) < np.inf:
        raise SplatFileError(source, f"{where} has a zero axis or one too long for floating point")
    lower, upper = _limits(source, element, kind, where)
    return {
        "name": name,
        "type": kind,
        **ends,
        "origin": _pose(source, element, where),
        "axis": axis,
        "lower": lower,
        "upper": upper,
        "mimic": _mimic(source, element, where),
    }


def _limits(source, element, kind, where):
    if kind not in ("revolute", "prismatic"):
        return -np.inf, np.inf
    limit = element.find("limit")
    if limit is None:
        warnings.warn(
            f"{source}: {where} ({kind}) has no <limit> (URDF requires one); left unlimited",
            SplatFileWarning,
            stacklevel=4,
        )
        return -np.inf, np.inf
    lower = _numbers(source, limit.get("lower", "0"), 1, f"{where} limit lower")[0]
    upper = _numbers(source, limit.get("upper", "0"), 1, f"{where} limit upper")[0]
    if lower > upper:
        warnings.warn(
            f"{source}: {where}: limit lower {lower:g} is above upper {upper:g}; swapped",
            SplatFileWarning,
            stacklevel=4,
        )
        lower, upper = upper, lower
    return lower, upper


def _mimic(source, element, where):
    tag = element.find("mimic")
    if tag is None:
        return None
    target = _attr(source, tag, "joint", "mimic")
    multiplier = _numbers(source, tag.get("multiplier", "1"), 1, f"{where} mimic multiplier")[0]
    offset = _numbers(source, tag.get("offset", "0"), 1, f"{where} mimic offset")[0]
    return (target, multiplier, offset)


def _rgba(source, material, where):
    tag = material.find("color")
    if tag is None:
        return None
    return tuple(_numbers(source, tag.get("rgba", ""), 4, f"{where} color rgba"))


def _materials(robot, source):
    """Named material colours, from anywhere in the file (URDF materials are global by name)."""
    named = {}
    for material in robot.iter("material"):
        name = material.get("name")
        rgba = _rgba(source, material, f"material '{name}'")
        if name and rgba is not None:
            named.setdefault(name, rgba)
    return named


def _visuals(source, link, materials, resolver):
    name = link.get("name")
    out = []
    for k, visual in enumerate(link.findall("visual")):
        where = f"link '{name}' visual {k}"
        geometry = visual.find("geometry")
        shape = next(iter(geometry), None) if geometry is not None else None
        if shape is None:
            raise SplatFileError(source, f"{where} has no <geometry> shape")
        material = visual.find("material")
        rgba = None
        if material is not None:
            rgba = _rgba(source, material, where) or materials.get(material.get("name"))
        item = Visual(name, _origin(source, visual, where), shape.tag, rgba=rgba, name=visual.get("name", ""))
        if shape.tag == "box":
            item.size = tuple(_numbers(source, shape.get("size", ""), 3, f"{where} box size"))
        elif shape.tag == "cylinder":
            item.size = (_positive(source, shape, "radius", where), _positive(source, shape, "length", where))
        elif shape.tag == "sphere":
            item.size = (_positive(source, shape, "radius", where),)
        elif shape.tag == "mesh":
            item.path = resolver.resolve(_attr(source, shape, "filename", "mesh"), where)
            if shape.get("scale") is not None:
                item.scale = _numbers(source, shape.get("scale"), 3, f"{where} mesh scale")
        else:
            raise SplatFileError(source, f"{where} has geometry <{shape.tag}>; supported: box, cylinder, sphere, mesh")
        out.append(item)
    return out


def _positive(source, shape, key, where):
    value = _numbers(source, shape.get(key, ""), 1, f"{where} {shape.tag} {key}")[0]
    if value <= 0:
        raise SplatFileError(source, f"{where}: {shape.tag} {key} {value:g} is not positive")
    return value


class _Resolver:
    """Mesh filenames to files, under io.policy's reading rule (see the module notes): only regular
    files under the allowed roots (the URDF's folder, then the package paths) are returned, and a
    refused name, a missing file and a special file give the same error."""

    def __init__(self, urdf_path, package_paths, allow_outside=False):
        self.urdf = Path(urdf_path).resolve()
        self.allow_outside = allow_outside
        self.roots = [self.urdf.parent, *package_search_path(package_paths)]

    def resolve(self, filename, where):
        for reference, base in self._candidates(filename):
            try:
                return referenced_file(self.urdf, reference, self.roots, base, self.allow_outside, "mesh")
            except SplatFileError:
                continue
        roots = ", ".join(f"'{r}'" for r in self.roots)
        raise SplatFileError(
            self.urdf,
            f"{where}: mesh '{filename}' not found among the regular files under {roots} (names outside "
            f"them are not followed unless allowed; {self._hint(filename)})",
        )

    def _hint(self, filename):
        """What to pass for a package the URDF itself lies in (robot/urdf/robot.urdf naming
        package://robot/meshes/...): told from the URDF's own path alone, so it says nothing of
        what exists on disk."""
        package = unquote(filename[len("package://") :]).partition("/")[0] if filename.startswith("package://") else ""
        home = next((d for d in self.urdf.parents if package and d.name == package), None)
        if home is None or home.parent in self.roots:
            return "add a package's folder with a package path"
        return f"the URDF lies in a folder named '{package}': a package path of '{home.parent}' would allow it"

    def _candidates(self, filename):
        """(reference, folder it is relative to) pairs to try in turn."""
        if filename.startswith("package://"):
            package, _, rest = unquote(filename[len("package://") :]).partition("/")
            searched = self.roots + (list(self.urdf.parents) if self.allow_outside else [])
            pairs = [(f"{package}/{rest}", d) for d in searched]
            pairs += [(rest, d) for d in searched if d.name == package]
            return pairs + [(rest, self.urdf.parent)]  # pybullet's data: the bare rest beside the URDF
        if filename.startswith("file://"):
            return [(unquote(filename[len("file://") :]), self.urdf.parent)]
        return [(filename, self.urdf.parent)]


def package_search_path(package_paths: Iterable[str | os.PathLike] = ()) -> list[Path]:
    """The folders package:// meshes are looked up in: `package_paths`, then the ROS_PACKAGE_PATH
    environment variable. Both are the user's own choice (whoever runs the reader set the variable),
    so both are allowed roots for the meshes a URDF names, beside the URDF's own folder."""
    env = [p for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
    return [Path(p).expanduser().resolve() for p in [*package_paths, *env]]
