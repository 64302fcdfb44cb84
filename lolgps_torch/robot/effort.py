"""Torque and velocity limits for actuated joints described without one.

ROS-Industrial descriptions (KUKA KR 16, KR 120, KR 210; ABB IRB 140) publish ``effort="0"``
on every joint as a placeholder for "not given".  The method needs a limit: the torque sent is
``clip(u + g(q), -effort, effort)``, the action cost is in units of ``effort`` and the gym
environment scales its normalised actions by it.  Such a joint gets one derived from the arm's
own rigid-body model (:mod:`.rigid_body`), at standard gravity:

``effort_j = EFFORT_MARGIN * max(G_j, I_j * g / reach)``

* ``G_j``, the largest gravity torque joint j holds, ``max |g_j(q)|``, and ``I_j``, its largest
  effective inertia ``max M_jj(q)``, both over :data:`POSES` poses drawn uniformly within the
  joint limits (seeded, so a description always gets the same limits);
* ``reach``, the largest distance of the peg tip from the first actuated joint's origin over
  the same poses; ``g / reach`` is the angular acceleration at which the tip accelerates at
  ``g``.  The term ``I_j g / reach`` is a floor for joints that hold little or no gravity
  torque (a wrist roll joint's ``G_j`` is ~0): each can still accelerate what it carries as
  fast as gravity would the outstretched arm;
* ``EFFORT_MARGIN = 3``: among the published arms that give their limits, ``effort / G`` at
  the shoulder (the most loaded joint) is 1.6 to 2.9 on the Panda, xArm 6, UR3e and UR5e and
  5.4 to 18.5 on the KUKA iiwa and the Trossen arms; the smallest ``effort / I`` of each is 14
  to 349 rad/s^2, and ``3 g / reach`` on them 22 to 38 (docs/RESULTS.md at c902895, section 10.1).  A
  margin of 3 leaves twice the worst gravity load for motion, between the two groups.

Both terms scale with the arm (torques as mass times length times g), so no arm needs a
constant of its own.

A joint published without a velocity limit (none, or ``velocity="0"``; an MJCF arm has none)
gets one from the same poses, as the speed at which it alone moves the peg tip at
:data:`TIP_SPEED`, at most :data:`JOINT_SPEED`:

``v_j = min(TIP_SPEED / r_j, JOINT_SPEED)``

* ``r_j``, the largest distance of the peg tip from joint j's axis over the poses;
* ``TIP_SPEED = 1.5 m/s``: the published limits of the KUKA iiwa 14, the Panda and the xArm 6
  move the tip at ``v_j r_j`` = 1.7, 2.5 and 3.0 m/s by their first joint (the tip speed a
  maker allows the whole arm), so 1.5 is below each;
* ``JOINT_SPEED = 2.3 rad/s`` caps the joints near the tip (``r_j`` small, the last one 0): the
  wrists of the same arms are published at 2.27 to 3.14 rad/s.

A derived limit is never faster than those arms allow a joint of the same lever.
"""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import replace

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.validate import ArmWarning

EFFORT_MARGIN = 3.0
POSES = 1024
STANDARD_GRAVITY = 9.81
TIP_SPEED = 1.5  # m/s
JOINT_SPEED = 2.3  # rad/s


def poses(arm: ArmSpec) -> Tensor:
    """:data:`POSES` joint angles ``[POSES, n]`` drawn uniformly (seed 0) within the limits."""
    lower, upper = (torch.tensor(b, dtype=torch.float64) for b in (arm.lower, arm.upper))
    draw = torch.rand(
        POSES, arm.dof, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    return lower + (upper - lower) * draw


def joint_loads(arm: ArmSpec) -> tuple[Tensor, Tensor, float]:
    """Over :func:`poses`, at standard gravity: each actuated joint's largest gravity torque
    ``max |g_j(q)|`` (N m, ``[n]``), its largest effective inertia ``max M_jj(q)`` (kg m^2,
    ``[n]``), and the largest distance (m) of the peg tip from the first actuated joint's
    origin."""
    dynamics = ArmDynamics(arm, gravity=STANDARD_GRAVITY)
    q = poses(arm)
    gravity = dynamics.gravity_torque(q).abs().amax(0)
    inertia = torch.diagonal(dynamics.mass_matrix(q), dim1=-2, dim2=-1).amax(0)
    frames = dynamics.frames(q)
    tip = dynamics.points(frames)[..., 0, :]
    reach = float((tip - frames.p[..., 0, :]).norm(dim=-1).max())
    return gravity, inertia, reach


def derived_effort(arm: ArmSpec) -> tuple[float, ...]:
    """Each actuated joint's torque limit derived from the arm (N m), as the module docstring
    states: ``EFFORT_MARGIN * max(G_j, I_j * g / reach)``."""
    gravity, inertia, reach = joint_loads(arm)
    floor = inertia * STANDARD_GRAVITY / reach
    return tuple(float(v) for v in EFFORT_MARGIN * torch.maximum(gravity, floor))


def joint_levers(arm: ArmSpec) -> Tensor:
    """Each actuated joint's largest distance (m, ``[n]``) of the peg tip from its axis, over
    :func:`poses`."""
    dynamics = ArmDynamics(arm, gravity=STANDARD_GRAVITY)
    frames = dynamics.frames(poses(arm))
    axes = dynamics.motion_subspace(frames)[..., :3]  # [POSES, n, 3], unit
    lever = dynamics.points(frames)[..., None, 0, :] - frames.p  # tip from each joint's origin
    radial = lever - (lever * axes).sum(-1, keepdim=True) * axes
    return radial.norm(dim=-1).amax(0)


def check_speeds(speeds: Sequence[float]) -> None:
    """Raise :class:`LolgpsError` unless every one of ``speeds`` (``--velocity-limit``) is
    positive and finite."""
    bad = [v for v in speeds if not (math.isfinite(v) and v > 0.0)]
    if bad:
        raise LolgpsError(f"--velocity-limit must be positive and finite, got {bad[0]}")


def derived_velocity(arm: ArmSpec) -> tuple[float, ...]:
    """Each actuated joint's velocity limit derived from the arm (rad/s), as the module
    docstring states: ``min(TIP_SPEED / r_j, JOINT_SPEED)``."""
    lever = joint_levers(arm).clamp(min=TIP_SPEED / JOINT_SPEED)
    return tuple(float(v) for v in TIP_SPEED / lever)


def with_derived_limits(
    arm: ArmSpec, effort: Sequence[str], velocity: Sequence[str], path: str
) -> ArmSpec:
    """``arm`` with the torque limits of the joints ``effort`` and the velocity limits of the
    joints ``velocity`` (each published as 0 or not at all) derived from the arm
    (module docstring), in its URDF text too; one :class:`ArmWarning` per kind names the values
    used."""
    derived = {"effort": dict(zip(arm.joint_names, arm.effort, strict=True)),
               "velocity": dict(zip(arm.joint_names, arm.velocity, strict=True))}  # fmt: skip
    tree = ET.fromstring(arm.urdf_text)
    kinds = (
        ("effort", effort, derived_effort, "N m", f"{EFFORT_MARGIN:g} x the larger of the "
         "joint's largest gravity torque and the torque that accelerates its load at g / reach"),
        ("velocity", velocity, derived_velocity, "rad/s", f"the speed that moves the peg tip "
         f"at {TIP_SPEED:g} m/s, at most {JOINT_SPEED:g} rad/s (or give --velocity-limit)"),
    )  # fmt: skip
    joints = {joint.get("name"): joint for joint in tree.findall("joint")}
    for attr, names, derive, unit, how in kinds:
        values = dict(zip(arm.joint_names, derive(arm), strict=True)) if names else {}
        for name in names:
            derived[attr][name] = values[name]
            limit = joints[name].find("limit")
            if limit is None:  # a continuous joint published without one
                limit = ET.SubElement(joints[name], "limit")
            limit.set(attr, repr(values[name]))
            warnings.warn(
                f"{path}: joint {name!r}: <limit> {attr} is not given (0); using "
                f"{values[name]:.4g} {unit}, {how}; set {attr} to its real limit ({unit})",
                ArmWarning,
                stacklevel=3,
            )
    return replace(
        arm,
        urdf_text=ET.tostring(tree, encoding="unicode"),
        effort=tuple(derived["effort"][n] for n in arm.joint_names),
        velocity=tuple(derived["velocity"][n] for n in arm.joint_names),
    )
