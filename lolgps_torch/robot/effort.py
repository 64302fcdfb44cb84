"""Torque limits for actuated joints described without one.

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
  to 349 rad/s^2, and ``3 g / reach`` on them 22 to 38 (docs/RESULTS.md section 10.1).  A
  margin of 3 leaves twice the worst gravity load for motion, between the two groups.

Both terms scale with the arm (torques as mass times length times g), so no arm needs a
constant of its own.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec

EFFORT_MARGIN = 3.0
POSES = 1024
STANDARD_GRAVITY = 9.81


def joint_loads(arm: ArmSpec) -> tuple[Tensor, Tensor, float]:
    """Over :data:`POSES` poses drawn uniformly (seed 0) within the joint limits, at standard
    gravity: each actuated joint's largest gravity torque ``max |g_j(q)|`` (N m, ``[n]``), its
    largest effective inertia ``max M_jj(q)`` (kg m^2, ``[n]``), and the largest distance (m)
    of the peg tip from the first actuated joint's origin."""
    dynamics = ArmDynamics(arm, gravity=STANDARD_GRAVITY)
    lower, upper = (torch.tensor(b, dtype=torch.float64) for b in (arm.lower, arm.upper))
    draw = torch.rand(
        POSES, arm.dof, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    q = lower + (upper - lower) * draw
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
