"""The arm in a URDF's tree of joints (yourdfpy's model): the chain from the base link to the
end effector, detected where it is not named (below the arm, a hand or gripper and its tool
frame), the joints of the chain the method actuates, and their limits."""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.validate import ArmWarning

if TYPE_CHECKING:
    import yourdfpy

ACTUATED = ("revolute", "continuous")
# words published descriptions use in the joint names of grippers and hands
_GRIPPER_WORDS = ("finger", "grip", "jaw", "knuckle", "claw", "thumb")
# words in the link names of sensors mounted on a wrist, which are no tool frame
_SENSOR_WORDS = ("camera", "optical", "imu", "accel", "lidar", "laser", "range", "depth")


def arm_chain(
    robot: yourdfpy.URDF, root: str, path: str, ee_link: str | None, base_link: str | None
) -> tuple[str, str, list[yourdfpy.Joint]]:
    """The arm's base link (``base_link``, else the root), its end-effector link (``ee_link``,
    else detected below the base link) and the joints from the base link to the end effector;
    unknown links, and a base link off the path from the root to the end effector, are
    errors."""
    parent_joint = {j.child: j for j in robot.robot.joints}
    links = [link.name for link in robot.robot.links]
    if not any(j.type in ACTUATED for j in robot.robot.joints):
        raise LolgpsError(f"{path}: URDF has no revolute or continuous joints to actuate")
    if base_link is not None and base_link not in links:
        raise LolgpsError(f"unknown base link {base_link!r}; links are: {', '.join(links)}")
    start = base_link or root
    if ee_link is None:
        ee_link = _detect_ee_link(robot, start, path)
    elif ee_link not in links:
        raise LolgpsError(f"unknown end-effector link {ee_link!r}; links are: {', '.join(links)}")
    full, link = [], ee_link
    while link in parent_joint:
        full.append(parent_joint[link])
        link = parent_joint[link].parent
    full.reverse()
    above = [j.parent for j in full]
    if start not in (*above, ee_link):
        raise LolgpsError(
            f"base link {start!r} is not on the chain from the root to {ee_link!r}; the links "
            f"on it are: {', '.join(above)}"
        )
    return start, ee_link, full[above.index(start) :] if start in above else []


def _is_arm_joint(j: yourdfpy.Joint) -> bool:
    """A joint the method actuates: revolute or continuous, driven by itself (no mimic)."""
    return j.type in ACTUATED and j.mimic is None


def actuated_joints(chain: list[yourdfpy.Joint], ee_link: str) -> list[yourdfpy.Joint]:
    """The actuated joints of the chain from the base link to ``ee_link``; its mimic, prismatic
    and other joints are held."""
    actuated = [j for j in chain if _is_arm_joint(j)]
    if not actuated:
        raise LolgpsError(
            f"end-effector link {ee_link!r} is not downstream of any actuated joint below the "
            f"base link; name another with --ee-link (or --base-link)"
        )
    locked = [j.name for j in chain if j.type not in (*ACTUATED, "fixed")]
    if locked:
        warnings.warn(
            f"joint(s) {', '.join(map(repr, locked))} on the chain to {ee_link!r} are held "
            f"fixed (--hold JOINT=VALUE sets where; --base-link LINK starts the arm below "
            f"them): only revolute and continuous joints are actuated",
            ArmWarning,
            stacklevel=3,
        )
    return actuated


def joint_limits(j: yourdfpy.Joint) -> tuple[float, float, float, float]:
    """(lower, upper, effort, velocity) of a checked joint
    (:func:`~lolgps_torch.robot.validate.check_actuated_limit`; effort and velocity 0 where
    they are not given); continuous joints get [-pi, pi] for placement."""
    lim = j.limit
    if lim is None:  # a continuous joint published without a <limit>
        return -math.pi, math.pi, 0.0, 0.0
    if not bounded(j):
        lower, upper = -math.pi, math.pi
    else:
        lower, upper = float(lim.lower), float(lim.upper)
    return lower, upper, float(lim.effort or 0.0), float(lim.velocity or 0.0)


def bounded(j: yourdfpy.Joint) -> bool:
    """Whether the actuated joint ``j`` has position limits (not continuous, both given)."""
    lim = j.limit
    return j.type != "continuous" and lim is not None and None not in (lim.lower, lim.upper)


def _is_gripper(j: yourdfpy.Joint) -> bool:
    """A gripper's joint, by the words published descriptions use in their names (not in
    link names: several arms call their wrist link ``gripper_link``)."""
    return any(word in j.name.lower() for word in _GRIPPER_WORDS)


def _hand_drivers(children: dict[str, list[yourdfpy.Joint]]) -> set[str]:
    """The joints that a sibling joint (one of the same parent link) mimics: a hand's driving
    joint, whose fingers follow it (Romeo's ``LHand``, beside ``LFinger21``, ``LFinger31`` and
    ``LThumb1``), whatever its name."""
    return {
        j.mimic.joint
        for siblings in children.values()
        for j in siblings
        if j.mimic is not None and any(k.name == j.mimic.joint for k in siblings)
    }


def _detect_ee_link(robot: yourdfpy.URDF, root: str, path: str, grippers: bool = True) -> str:
    """The end of the arm: follow the actuated joints down from the root and stop at the link
    below which the tree splits into branches no deeper than the path so far (a hand or
    gripper) or has no actuated joint left; then take the deepest link fixed to it (a flange,
    tool or TCP frame; among equally deep ones, one with no child link), skipping gripper
    parts and wrist cameras.  Gripper joints (:func:`_is_gripper`, and a hand's driving joint,
    :func:`_hand_drivers`), mimic and prismatic joints never count,
    unless ``grippers`` is False: that is the second try when the first passes no actuated
    joint (a robot finger's joints are all named ``finger_...``).  Two equally deep arms are
    an error naming where each ends.
    """
    children: dict[str, list[yourdfpy.Joint]] = {}
    for j in robot.robot.joints:
        children.setdefault(j.parent, []).append(j)
    hands = _hand_drivers(children)

    def skipped(j: yourdfpy.Joint) -> bool:
        return grippers and (_is_gripper(j) or j.name in hands)

    @functools.cache
    def depth(link: str) -> int:  # most actuated joints on a path below link
        arm = [j for j in children.get(link, []) if not skipped(j)]
        return max((_is_arm_joint(j) + depth(j.child) for j in arm), default=0)

    def branches(link: str) -> list[tuple[int, str]]:
        arm = [j for j in children.get(link, []) if not skipped(j)]
        found = [(_is_arm_joint(j) + depth(j.child), j.child) for j in arm]
        return [(d, c) for d, c in found if d]

    def descend(link: str, passed: int) -> tuple[str, int]:
        """Down from ``link`` (``passed`` arm joints above it) to where the arm ends."""
        while branches(link):
            found = branches(link)
            best = max(d for d, _ in found)
            deepest = [c for d, c in found if d == best]
            if len(found) > 1 and passed >= best:
                break  # a hand below the arm
            if len(deepest) > 1:
                ends = [
                    _tool_frame(
                        children, descend(c, passed + _below_arm_joint(robot, c))[0], skipped
                    )
                    for c in deepest
                ]
                picks = " or ".join(f"--base-link {link} --ee-link {end}" for end in ends)
                raise LolgpsError(
                    f"{path}: the description has {len(deepest)} arms below link {link!r}, "
                    f"ending at {', '.join(ends)}: pick one with {picks}"
                )
            passed += _below_arm_joint(robot, deepest[0])
            link = deepest[0]
        return link, passed

    link, passed = descend(root, 0)
    if passed == 0 and grippers:
        return _detect_ee_link(robot, root, path, grippers=False)
    return _tool_frame(children, link, skipped)


def _tool_frame(
    children: dict[str, list[yourdfpy.Joint]],
    link: str,
    skipped: Callable[[yourdfpy.Joint], bool],
) -> str:
    """The deepest link fixed to ``link`` by joints not ``skipped``, breadth first, leaving out
    sensors (a wrist camera's links, by :data:`_SENSOR_WORDS`); among equally deep ones a frame
    with nothing below it (a tool frame, not a gripper's base), then the first found; ``link``
    itself if there is none."""
    fixed, frontier = [(0, link)], [(0, link)]
    while frontier:
        level, here = frontier.pop(0)
        for j in children.get(here, []):
            sensor = any(word in j.child.lower() for word in _SENSOR_WORDS)
            if j.type == "fixed" and not skipped(j) and not sensor:
                fixed.append((level + 1, j.child))
                frontier.append((level + 1, j.child))
    return max(fixed, key=lambda item: (item[0], item[1] not in children))[1]


def _below_arm_joint(robot: yourdfpy.URDF, link: str) -> bool:
    """Whether ``link`` hangs from an actuated joint (:func:`_is_arm_joint`)."""
    return _is_arm_joint(next(j for j in robot.robot.joints if j.child == link))
