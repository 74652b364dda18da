"""Articulation: splats that follow bones and joints.

One import for both halves: kinematic trees and forward kinematics (core.kinematics; URDF files
through io.urdf) and skinning of whole clouds with linear-blend or dual-quaternion blending
(core.skinning). Typical use:

    tree = read_urdf("robot.urdf")                        # or KinematicTree.from_rest_matrices(...)
    binding = Binding.rigid(link_of_splat)                # or Binding.from_dense(weights, 4)
    posed = skin(cloud, binding, tree.deform_matrices(q), mode="dqs")
"""

from .kinematics import (
    JOINT_DOF,
    KinematicsError,
    KinematicTree,
    axis_angle_matrices,
    quaternions_to_rotvec,
    rotvec_to_quaternions,
    transforms,
)
from .skinning import MIN_TOTAL_WEIGHT, Binding, BonePose, SkinningError, deform_matrices, skin, skin_centres

__all__ = [
    "JOINT_DOF",
    "KinematicsError",
    "KinematicTree",
    "axis_angle_matrices",
    "quaternions_to_rotvec",
    "rotvec_to_quaternions",
    "transforms",
    "MIN_TOTAL_WEIGHT",
    "Binding",
    "BonePose",
    "SkinningError",
    "deform_matrices",
    "skin",
    "skin_centres",
]
