"""What the method needs to know about a URDF arm, read once with yourdfpy after the XML has
been checked against what PyBullet and pytorch-kinematics need (:mod:`.validate`).

yourdfpy (and trimesh, which it imports) is imported only when a URDF is parsed, and the
:class:`ArmSpec` itself lives in :mod:`.spec`, so processes that merely receive one (the
evaluation's workers) do not pay for them.

An :class:`ArmSpec` is the single description that drives both PyBullet (joint names are
mapped to body joint indices) and pytorch-kinematics (the serial chain to the point
frame), so the two cannot disagree; the peg it ends in is :mod:`.peg`'s.

The loader's steps, in order: the chain from the base link to the end effector and its
actuated joints (:mod:`.chain`), the joints off it held fixed and the text both readers
accept (:mod:`.urdf_edit`: fixed links merged, meshes resolved, unused shapes and other tools'
extensions dropped), the peg, and the limits a description does not give derived from the
arm (:mod:`.effort`).
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.chain import actuated_joints, arm_chain, bounded, joint_limits
from lolgps_torch.robot.effort import with_derived_limits
from lolgps_torch.robot.packages import resolve_mesh
from lolgps_torch.robot.peg import (
    ATTACHED_PEG,
    ATTACHED_PEG_TIP,
    CARRIED_PEG_TIP,
    PegConfig,
    attach_peg,
    auto_axis,
    carried_peg_radius,
)
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.urdf_edit import (
    PYBULLET_LINKS,
    lock_joints,
    merge_fixed_leaves,
    portable_text,
)
from lolgps_torch.robot.validate import check_actuated_limit, check_moved_mass, validate_urdf

if TYPE_CHECKING:
    import yourdfpy

# a prefix of an element's or attribute's name, as in <drake:member> or drake:acceleration="..."
_PREFIXED = re.compile(r"(?:<|</|\s)([A-Za-z_][\w.-]*):[A-Za-z_][\w.-]*(?=[\s=/>])")


def load_arm(
    path: str,
    ee_link: str | None = None,
    peg: PegConfig | None = None,
    package_path: Sequence[str] = (),
    base_link: str | None = None,
    hold: Mapping[str, float] | None = None,
    mjcf: bool = False,
) -> ArmSpec:
    """Read and validate a URDF arm; raise :class:`LolgpsError` with a one-line reason.

    :param path: the URDF file, as published (``package://`` mesh URIs are searched for, see
        :mod:`.packages`; meshes that are not found are only warned about).
    :param ee_link: the end-effector link; detected below ``base_link`` when None
        (:func:`~lolgps_torch.robot.chain._detect_ee_link`).
    :param peg: the peg attached when the URDF carries none.
    :param package_path: folders searched for ROS packages after ``ROS_PACKAGE_PATH``.
    :param base_link: the link the arm's chain starts from (the root when None); every joint
        above it is held fixed, as is every joint off the chain.
    :param hold: positions (rad or m) of held joints; the others are held at 0, or at the
        middle of their limits when 0 is outside them.
    :param mjcf: ``path`` is an MJCF file, converted to URDF (:mod:`.mjcf`).
    """
    peg = peg or PegConfig()
    raw, tree, robot, root = _parse(path, package_path, mjcf)
    parent_joint = {j.child: j for j in robot.robot.joints}
    links = [link.name for link in robot.robot.links]
    start, ee_link, chain = arm_chain(robot, root, path, ee_link, base_link)
    actuated = actuated_joints(chain, ee_link)
    elements = {j.get("name"): j for j in tree.findall("joint")}
    unknown = [
        j.name
        for j in actuated
        if check_actuated_limit(elements[j.name], f"{path}: joint {j.name!r}")
    ]
    held = lock_joints(tree, {j.name for j in actuated}, dict(hold or {}))

    carries_peg = CARRIED_PEG_TIP in links and ee_link == CARRIED_PEG_TIP
    if carries_peg:
        point_link, peg_link = CARRIED_PEG_TIP, parent_joint[CARRIED_PEG_TIP].parent
        peg_radius = carried_peg_radius(robot, peg_link, path)
    else:
        if ATTACHED_PEG in links:
            raise LolgpsError(
                f"{path}: link name {ATTACHED_PEG!r} is reserved for the attached peg"
            )
        point_link, peg_link, peg_radius = ATTACHED_PEG_TIP, ATTACHED_PEG, peg.radius
    kept = {root, ee_link, point_link, peg_link, *(n for j in chain for n in (j.parent, j.child))}
    merge_fixed_leaves(tree, kept, PYBULLET_LINKS - (0 if carries_peg else 2), path)
    text = portable_text(tree, path, package_path, peg_link)
    axis = ""
    if not carries_peg:
        axis = auto_axis(chain, actuated) if peg.axis == "auto" else peg.axis
        text = attach_peg(text, ee_link, peg, axis)
    massless = check_moved_mass(text, path)

    lims = [joint_limits(j) for j in actuated]
    arm = ArmSpec(
        urdf_text=text,
        source_path=os.path.abspath(path),
        source_sha256=hashlib.sha256(raw).hexdigest(),
        root_link=root,
        ee_link=ee_link,
        point_link=point_link,
        peg_link=peg_link,
        joint_names=tuple(j.name for j in actuated),
        lower=tuple(lim[0] for lim in lims),
        upper=tuple(lim[1] for lim in lims),
        effort=tuple(lim[2] for lim in lims),
        velocity=tuple(lim[3] for lim in lims),
        point_offsets=((0.0, 0.0, 0.0), (0.0, 0.0, -peg.point_separation)),
        peg_radius=peg_radius,
        peg_axis=axis,
        base_link=start,
        held=held,
        unbounded=tuple(j.name for j in actuated if not bounded(j)),
    )
    if massless:
        _check_mass_matrix(arm, massless, path)
    slow = [j.name for j, lim in zip(actuated, lims, strict=True) if lim[3] == 0.0]
    return with_derived_limits(arm, unknown, slow, path) if unknown or slow else arm


def _check_mass_matrix(arm: ArmSpec, massless: Sequence[str], path: str) -> None:
    """With massless driven links, joints can together make a motion that moves no mass (a
    massless wrist whose axes align): the mass matrix is then singular and no simulator can
    integrate the arm.  Checked at q = 0 (where the simulated world starts) and at random
    poses within the limits, with the inertias PyBullet uses."""
    lower, upper = (torch.tensor(b, dtype=torch.float64) for b in (arm.lower, arm.upper))
    draw = torch.rand(8, arm.dof, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    poses = torch.cat(
        [torch.zeros(1, arm.dof, dtype=torch.float64), lower + (upper - lower) * draw]
    )
    M = ArmDynamics(arm, inertia="pybullet").mass_matrix(poses)
    eig = torch.linalg.eigvalsh(M)
    singular = eig[:, 0] <= 1e-12 * eig[:, -1].clamp(min=1e-300)
    if bool(singular.any()):
        q = poses[int(torch.nonzero(singular)[0, 0])].tolist()
        raise LolgpsError(
            f"{path}: with link(s) {', '.join(map(repr, massless))} massless (no <inertial> "
            f"or mass 0) the mass matrix is singular at q = "
            f"[{', '.join(f'{v:.3g}' for v in q)}] rad (some joint motion moves no mass); "
            f"add their mass and inertia"
        )


def _parse(
    path: str, package_path: Sequence[str], mjcf: bool = False
) -> tuple[bytes, ET.Element, yourdfpy.URDF, str]:
    """The file's bytes, its XML tree, yourdfpy's model and the root link; one-line errors for
    bad files, raised before yourdfpy, pytorch-kinematics or PyBullet read them.  ``mjcf``:
    the file is MJCF, read as the URDF :func:`~lolgps_torch.robot.mjcf.mjcf_urdf` makes of it."""
    import yourdfpy  # here, not at the top: see the module docstring

    if not os.path.isfile(path):
        raise LolgpsError(f"{'MJCF' if mjcf else 'URDF'} not found: {path}")
    with open(path, "rb") as fh:
        raw = fh.read()
    if mjcf:
        from lolgps_torch.robot.mjcf import mjcf_urdf  # imports MuJoCo, an extra

        text = mjcf_urdf(path)
    else:
        text = declare_prefixes(raw.decode("utf-8", errors="replace"))
    if "<!ENTITY" in text:
        raise LolgpsError(f"{path}: URDF declares XML entities; they are not resolved")
    try:
        tree = ET.fromstring(text)
    except ET.ParseError as exc:
        raise LolgpsError(f"{path}: malformed XML ({exc})") from None
    root = validate_urdf(tree, path)
    try:
        robot = yourdfpy.URDF.load(
            io.BytesIO(text.encode("utf-8")),
            build_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
            filename_handler=lambda name: resolve_mesh(name, path, package_path) or name,
        )
    except Exception as exc:  # yourdfpy raises assorted types on schema errors
        raise LolgpsError(f"{path}: not a valid URDF ({type(exc).__name__}: {exc})") from None
    return raw, tree, robot, root


def declare_prefixes(text: str) -> str:
    """``text`` with a namespace declared on ``<robot>`` for every prefix it uses undeclared.

    Descriptions written for one tool carry that tool's extensions under a prefix they often
    do not declare (``<limit drake:acceleration=...>``, ``<drake:collision_filter_group>``);
    the XML is then not well formed, though the URDF readers skip what they do not know.  The
    declared elements and attributes are dropped later (:func:`portable_text`)."""
    used = set(_PREFIXED.findall(text)) - {"xml", "xmlns"}
    declared = set(re.findall(r"xmlns:([A-Za-z_][\w.-]*)\s*=", text))
    missing = sorted(used - declared)
    start = re.search(r"<robot\b", text)
    if not missing or start is None:
        return text
    names = "".join(f' xmlns:{p}="urn:undeclared:{p}"' for p in missing)
    return text[: start.end()] + names + text[start.end() :]
