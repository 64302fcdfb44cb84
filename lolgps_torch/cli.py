"""Shared command-line plumbing: flags derived from the config dataclasses, the arm/task flags
every script takes, checks of paths and devices before any work, and one-line errors."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import types
import typing
import warnings
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.franka import RealArmConfig
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig

Position = tuple[float, float]
DEFAULT_URDF = "robots/kuka_peg.urdf"  # the arm of a stream without --urdf, in the checkout


def run_parser(doc: str | None, conditions: Sequence[int]) -> argparse.ArgumentParser:
    """A parser for a script about a finished run: ``--run RUN`` (its folder) and
    ``--conditions C ...`` (indices of its conditions, ``conditions`` by default), with
    ``doc`` as its description."""
    parser = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="a run folder")
    parser.add_argument("--conditions", type=int, nargs="+", default=list(conditions))
    return parser


def _field_hint(owner: object, name: str) -> Any:
    """The resolved type annotation of field ``name`` of the dataclass instance ``owner``."""
    return typing.get_type_hints(type(owner))[name]


def _param_help(owner: object, name: str) -> str:
    """The text of ``:param name:`` in the docstring of ``owner``'s class, on one line."""
    doc = type(owner).__doc__ or ""
    found = re.search(rf":param {name}:(.*?)(?=:param |\n\s*\n|$)", doc, re.DOTALL)
    if found is None:
        raise TypeError(f"{type(owner).__name__} documents no :param {name}:")
    return " ".join(found.group(1).split()).rstrip(".").replace("%", "%%")


def _or_none(kind: type) -> Callable[[str], Any]:
    """The parser of an optional number's flag: ``text`` as a ``kind``, or None for ``none``
    (named as ``kind``, so that argparse's error names the type)."""

    def parse(text: str) -> Any:
        return None if text.lower() == "none" else kind(text)

    parse.__name__ = kind.__name__
    return parse


def _argument(hint: Any, flag: str) -> dict[str, Any]:
    """argparse keywords for a field of type ``hint``: its type, choices for a ``Literal``,
    ``nargs`` for a tuple; a bool is a switch (``--no-...`` turns it off); an optional number
    takes ``none`` as well."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        (hint,) = [a for a in args if a is not type(None)]
        if hint in (int, float):  # "none" sets the field to None
            return {"type": _or_none(hint)}
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        if flag.startswith("no-"):
            return {"action": "store_false"}
        return {"action": argparse.BooleanOptionalAction}
    if origin is Literal:
        return {"type": type(args[0]), "choices": list(args)}
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return {"type": args[0], "nargs": "+"}
    if hint in (int, float, str):
        return {"type": hint}
    raise TypeError(f"no command-line flag for a field of type {hint} (--{flag})")


def _leaf(config: object, path: str) -> tuple[object, str]:
    """The dataclass instance holding the dotted field ``path`` of ``config``, and the name."""
    *owners, name = path.split(".")
    for owner in owners:
        config = getattr(config, owner)
    return config, name


def _replaced(config: Any, path: str, value: Any) -> Any:
    """``config`` with the dotted field ``path`` set to ``value`` (frozen dataclasses)."""
    name, _, rest = path.partition(".")
    if rest:
        value = _replaced(getattr(config, name), rest, value)
    return dataclasses.replace(config, **{name: value})


@dataclass(frozen=True)
class ConfigFlags:
    """Command-line flags for the fields of a config dataclass.

    Every top-level field of ``default`` that is a number, string, bool, ``Literal`` or tuple
    becomes ``--field-name`` (type, default, choices and help from the class and its
    docstring's ``:param:`` lines), except those in ``skip``; ``renames`` maps further flags
    onto dotted field paths (nested ones, or several at once), taking type and help from the
    first. A bool flag named ``no-...`` sets its fields to False.

    :param default: the configuration the flags start from.
    :param renames: flag name (without ``--``) -> the field paths it sets.
    :param skip: top-level fields without a flag of their own.
    """

    default: Any
    renames: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    skip: Collection[str] = ()

    def table(self) -> dict[str, tuple[str, ...]]:
        """Every flag name and the field paths it sets."""
        covered = {path for paths in self.renames.values() for path in paths} | set(self.skip)
        derived = {
            f.name.replace("_", "-"): (f.name,)
            for f in dataclasses.fields(self.default)
            if f.name not in covered and not dataclasses.is_dataclass(getattr(self.default, f.name))
        }
        return {**derived, **self.renames}

    def add_to(
        self, parser: argparse.ArgumentParser | argparse._ArgumentGroup, inherited: str = ""
    ) -> None:
        """Add the flags to ``parser``; with ``inherited``, a flag left out keeps the value of
        the configuration :meth:`build` is given, which ``inherited`` names in the help."""
        for flag, paths in self.table().items():
            owner, name = _leaf(self.default, paths[0])
            default = None if inherited else getattr(owner, name)
            text = _param_help(owner, name)
            if inherited:
                text += f" (default: {inherited})"
            elif not flag.startswith("no-"):
                text += " (default %(default)s)"
            parser.add_argument(
                f"--{flag}",
                default=default,
                help=text,
                **_argument(_field_hint(owner, name), flag),
            )

    def build(self, args: argparse.Namespace, base: Any = None) -> Any:
        """The configuration the parsed flags describe (its ``__post_init__`` checks apply):
        ``base`` with the flags given (those added with ``inherited``), else the default with
        every flag."""
        config = self.default if base is None else base
        for flag, paths in self.table().items():
            value = getattr(args, flag.replace("-", "_"))
            if base is not None and value is None:
                continue
            value = tuple(value) if isinstance(value, list) else value
            for path in paths:
                config = _replaced(config, path, value)
        return config


PLANT_FLAGS = ConfigFlags(
    PlantConfig(),
    renames={
        "plant-inertia-scale": ("inertia_scale",),
        "plant-seed": ("seed",),
        "payload": ("payload",),
        "gravity-compensation": ("gravity_compensation",),
        "joint-friction": ("joint_friction",),
        "obs-noise": ("obs_noise",),
        "action-delay": ("action_delay",),
        "limits": ("limits",),
    },
)

TASK_FLAGS = ConfigFlags(
    TaskConfig(urdf=""),
    renames={
        "peg-length": ("peg.length",),
        "peg-radius": ("peg.radius",),
        "peg-axis": ("peg.axis",),
        "q0": ("placement.q0",),
        "friction": ("world.friction",),
        "known-delay": ("world.known_delay",),
        "compensate-gravity": ("world.compensate_gravity",),
        "action-weight": ("cost.action_weight",),
        "speed-weight": ("cost.speed_weight",),
        "speed-free": ("cost.speed_free",),
        "descent-height": ("cost.descent_height",),
        "descent-steps": ("cost.descent_steps",),
        **{flag: (f"plant.{name}",) for flag, (name,) in PLANT_FLAGS.renames.items()},
    },
    skip=("urdf", "scale", "mjcf"),  # run_stream.py's --scale takes auto too
)


def add_task_arguments(parser: argparse.ArgumentParser, default_urdf: str | None = None) -> None:
    """Flags that pick the arm (``--urdf``, or ``--mjcf`` with ``--sim mujoco``), its peg, its
    start pose, the world and the cost."""
    group = parser.add_argument_group("arm")
    description = group.add_mutually_exclusive_group(required=default_urdf is None)
    description.add_argument("--urdf", default=default_urdf, help="the arm's URDF file")
    description.add_argument(
        "--mjcf",
        help="the arm's MJCF file, converted to URDF (needs --sim mujoco; --ee-link may name a "
        "body or a site)",
    )
    TASK_FLAGS.add_to(group)


def task_config(args: argparse.Namespace) -> TaskConfig:
    """The :class:`TaskConfig` the arm flags describe, its values checked."""
    if args.descent_height < 0.0 or args.descent_steps < 0:
        raise LolgpsError("--descent-height and --descent-steps must be >= 0")
    config: TaskConfig = TASK_FLAGS.build(args)
    if args.mjcf is not None:
        return dataclasses.replace(config, urdf=args.mjcf, mjcf=True)
    return dataclasses.replace(config, urdf=args.urdf)


ARM_FLAGS = ConfigFlags(RealArmConfig())


def add_arm_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of the arm the rollouts run on (``--arm franka --robot-ip IP``, its
    settings), docs/REAL_ARM.md."""
    ARM_FLAGS.add_to(parser.add_argument_group("real arm"))


def arm_config(args: argparse.Namespace) -> RealArmConfig:
    """The :class:`RealArmConfig` the arm flags describe, checked once all are set."""
    fields = dataclasses.fields(RealArmConfig)
    return RealArmConfig(**{f.name: getattr(args, f.name) for f in fields})


def scale_factor(text: str) -> float:
    """The FACTOR of ``--scale FACTOR``: a number in (0, 1] (:class:`TaskConfig` checks the
    range); anything else is a :class:`LolgpsError`."""
    try:
        return float(text)
    except ValueError:
        raise LolgpsError(f"--scale {text}: expected auto or a factor in (0, 1]") from None


def add_plant_arguments(parser: argparse.ArgumentParser) -> None:
    """The plant flags of a script that runs a saved run again: each one left out keeps the
    run's (:func:`plant_config`)."""
    PLANT_FLAGS.add_to(parser.add_argument_group("plant"), inherited="the run's")


def plant_config(args: argparse.Namespace, saved: PlantConfig) -> PlantConfig:
    """The run's plant ``saved`` with the plant flags given (:func:`add_plant_arguments`)."""
    plant: PlantConfig = PLANT_FLAGS.build(args, saved)
    return plant


def add_delay_argument(parser: argparse.ArgumentParser) -> None:
    """``--detect-delay``/``--no-detect-delay``: estimate the arm's command delay first."""
    parser.add_argument(
        "--detect-delay",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="estimate the arm's command delay from excitation rollouts before learning and "
        "allow for it, unless --known-delay is given (default: on)",
    )


def add_gravity_argument(parser: argparse.ArgumentParser) -> None:
    """``--detect-gravity``/``--no-detect-gravity``: find whether the arm compensates gravity."""
    parser.add_argument(
        "--detect-gravity",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="find from rollouts let go at the start pose whether the arm's commands are "
        "compensated for gravity before learning, and compensate them with the URDF's model "
        "where they are not, unless --compensate-gravity is given (default: on)",
    )


WORKERS_VARIABLE = "LOLGPS_WORKERS"


def add_workers_argument(parser: argparse.ArgumentParser) -> None:
    """``--workers``: the processes a batch of rollouts is spread over (PyBullet steps a world
    on one core); its default is ``$LOLGPS_WORKERS``, else the machine's cores."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes running each batch's rollouts, a world each; the results are the same "
        f"for any number (default: ${WORKERS_VARIABLE}, else this machine's cores)",
    )


def workers(args: argparse.Namespace) -> int:
    """The ``--workers`` value, or its default (:func:`add_workers_argument`), checked."""
    if args.workers is not None:
        value, source = args.workers, "--workers"
    elif WORKERS_VARIABLE in os.environ:
        text, source = os.environ[WORKERS_VARIABLE], WORKERS_VARIABLE
        try:
            value = int(text)
        except ValueError:
            raise LolgpsError(f"{source}={text!r}: expected a whole number") from None
    else:
        value, source = os.cpu_count() or 1, "--workers"
    if value < 1:
        raise LolgpsError(f"{source} {value}: must be at least 1")
    return int(value)


def check_device(name: str) -> torch.device:
    """The torch device ``name``, checked usable here; otherwise a :class:`LolgpsError`."""
    try:
        device = torch.device(name)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else "unusable"
        raise LolgpsError(f"--device {name}: {reason}") from None
    return device


def read_offsets(path: str, flag: str) -> list[Position]:
    """The hole offsets in the JSON file ``path``: a non-empty list of ``[dx, dy]`` pairs of
    finite numbers (m); anything else is a :class:`LolgpsError` naming ``flag``."""
    try:
        raw = json.loads(Path(path).read_text())
        offsets = [(float(dx), float(dy)) for dx, dy in raw]
    except OSError as error:
        raise LolgpsError(f"{flag} {path}: {error.strerror or error}") from None
    except (ValueError, TypeError) as error:
        raise LolgpsError(f"{flag} {path}: expected a JSON list of [dx, dy] ({error})") from None
    bad = [list(o) for o in offsets if not all(math.isfinite(v) for v in o)]
    if bad:
        raise LolgpsError(f"{flag} {path}: offsets must be finite numbers, got {bad[0]}")
    if not offsets:
        raise LolgpsError(f"{flag} {path} is empty")
    return offsets


_default_showwarning = warnings.showwarning


def _show_warning(message: Warning | str, category: type[Warning], *args: Any, **kw: Any) -> None:
    """An :class:`ArmWarning` as one ``warning:`` line; other warnings as Python prints them."""
    if issubclass(category, ArmWarning):
        print(f"warning: {message}", file=sys.stderr)
    else:
        _default_showwarning(message, category, *args, **kw)


def run(main: Callable[[], None]) -> None:
    """Run a script's main: a :class:`LolgpsError` becomes one ``error:`` line and exit 2.

    Torch runs on one intra-op thread (``LOLGPS_THREADS`` overrides): the tensors here are
    small, and a second thread only contends with the simulator and with parallel workers.
    """
    torch.set_num_threads(int(os.environ.get("LOLGPS_THREADS", "1")))
    warnings.showwarning = _show_warning
    try:
        main()
    except LolgpsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except BrokenPipeError:  # output piped into a reader that stopped (e.g. head)
        sys.stderr.close()
        sys.exit(1)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
