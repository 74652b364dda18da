"""URDF robot descriptions, kinematic part only: links, joints, origins, axes and limits.

Visual, collision and inertial elements (and their meshes) are ignored. The result is a
core.kinematics.KinematicTree whose links are the URDF links in topological order and whose
joint at each link is the URDF joint that has the link as its child.
"""

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..core.kinematics import KinematicsError, KinematicTree, rpy_matrices, transforms
from .common import SplatFileError, read_text

_TYPES = ("fixed", "revolute", "continuous", "prismatic")


def read_urdf(path):
    """Read a .urdf file into a KinematicTree; SplatFileError names the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise SplatFileError(path, "no such file")
    return parse_urdf(read_text(path), source=str(path))


def parse_urdf(text, source="<string>"):
    """Parse URDF XML text into a KinematicTree (`source` names it in error messages)."""
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as exc:
        raise SplatFileError(source, f"not valid XML: {exc}") from None
    if robot.tag != "robot":
        raise SplatFileError(source, f"root element is <{robot.tag}>, expected <robot>")
    links = [_attr(source, link, "name", "link") for link in robot.findall("link")]
    if not links:
        raise SplatFileError(source, "no <link> elements")
    if len(set(links)) != len(links):
        raise SplatFileError(source, "link names are not unique")
    joints = [_joint(source, j, set(links)) for j in robot.findall("joint")]
    if len({j["name"] for j in joints}) != len(joints):
        raise SplatFileError(source, "joint names are not unique")
    children = {j["child"] for j in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise SplatFileError(source, f"expected exactly one root link (a link that is no joint's child), "
                                     f"found {roots or 'none'}")
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
    origin = element.find("origin")
    xyz = _numbers(source, origin.get("xyz", "0 0 0"), 3, f"{where} origin xyz") if origin is not None else np.zeros(3)
    rpy = _numbers(source, origin.get("rpy", "0 0 0"), 3, f"{where} origin rpy") if origin is not None else np.zeros(3)
    axis_tag = element.find("axis")
    axis = _numbers(source, axis_tag.get("xyz", "1 0 0"), 3, f"{where} axis") if axis_tag is not None \
        else np.array([1.0, 0.0, 0.0])
    if kind != "fixed" and not 1e-12 <= np.linalg.norm(axis) < np.inf:
        raise SplatFileError(source, f"{where} has a zero axis or one too long for floating point")
    lower, upper = -np.inf, np.inf
    if kind in ("revolute", "prismatic"):
        limit = element.find("limit")
        if limit is None:
            raise SplatFileError(source, f"{where} ({kind}) has no <limit> (URDF requires one)")
        lower = _numbers(source, limit.get("lower", "0"), 1, f"{where} limit lower")[0]
        upper = _numbers(source, limit.get("upper", "0"), 1, f"{where} limit upper")[0]
        if lower > upper:
            raise SplatFileError(source, f"{where}: limit lower {lower} is above upper {upper}")
    return {"name": name, "type": kind, **ends, "origin": transforms(rpy_matrices(rpy), xyz),
            "axis": axis, "lower": lower, "upper": upper}
