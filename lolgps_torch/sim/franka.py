"""A real arm for the learner: the Franka (FR3 or Panda) through libfranka
(``--arm franka --robot-ip IP``; ``pip install -e '.[franka]'``).

- :class:`RealArmConfig`, the arm the rollouts run on and its settings.
- :class:`RealArm`, what the learner asks of any torque-controlled arm, named for what the arm
  does: :meth:`~RealArm.read_state`, :meth:`~RealArm.command_torque` (a torque over the arm's
  own gravity compensation, held at the arm's rate), :meth:`~RealArm.stop` (end the torque
  command, the arm holding where it is), :meth:`~RealArm.recover` (clear a reflex) and
  :meth:`~RealArm.move_to` (a slow joint-space move within the limits).  A fault of the arm's
  controller is an :class:`ArmFaultError`.
- :class:`FrankaArm`, that interface over libfranka.  The arm's 1 kHz loop runs in a process
  of its own (:func:`_serve`, forked: it imports no torch), so that the learner's work between
  control steps (the state vector, the controller) never starves the loop: the loop holds the
  latest command, rate-limited as libfranka's rate limiter does (:data:`TORQUE_RATE`), and
  ends the torque command with a fault when the learner's next command is late by more than
  the deadline (:attr:`RealArmConfig.deadline`); when the learner is gone (its end of the pipe
  closed, even by a kill) the loop ends its motion and exits.  A real-time kernel is asked
  for with ``--realtime``.

The world over such an arm is :mod:`lolgps_torch.sim.arm_world`'s.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import multiprocessing.connection
import signal
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, Protocol

import numpy as np

from lolgps_torch.errors import LolgpsError

FRANKA_INSTALL = "pip install -e '.[franka]'"
TICK = 0.001  # s: the Franka's control period
TORQUE_RATE = 1000.0  # N m/s: libfranka's bound on the commanded torque's rate, per joint
SETTLE = 0.25  # s: the end of a move held, for the arm to settle at rest
ANSWER = 10.0  # s: the longest the learner waits for the loop beyond the motion it asked for
ArmKind = Literal["simulated", "franka"]


@dataclass(frozen=True)
class RealArmConfig:
    """The arm the rollouts run on.

    :param arm: simulated (the simulator ``--sim`` names) or franka (a Franka FR3 or Panda
        through libfranka, at ``--robot-ip``; one rollout at a time).
    :param robot_ip: the arm's address (its FCI interface; Desk's "Activate FCI").
    :param move_speed: the fastest joint speed (rad/s) of the move back to the start pose
        between rollouts.
    :param deadline: the longest (s) the arm's loop holds a control step's command past its
        end waiting for the learner's next; beyond it the torque command ends as a fault.
    :param collision_torque: the arm's collision thresholds as a fraction of each joint's
        effort limit (``set_collision_behavior``; the force thresholds are
        ``collision_force``). :param collision_force: the Cartesian collision threshold (N).
    :param realtime: demand a real-time kernel (libfranka's kEnforce); off, kIgnore.
    :param yes: take each hole position as set (the offsets given are where the hole is)
        instead of asking the person at the arm to move it and press Enter.
    """

    arm: ArmKind = "simulated"
    robot_ip: str = ""
    move_speed: float = 0.4
    deadline: float = 0.2
    collision_torque: float = 0.6
    collision_force: float = 60.0
    realtime: bool = False
    yes: bool = False

    def __post_init__(self) -> None:
        if self.arm not in ("simulated", "franka"):
            raise LolgpsError(f"--arm must be simulated or franka, got {self.arm!r}")
        if self.arm == "franka" and not self.robot_ip:
            raise LolgpsError("--arm franka needs --robot-ip (the arm's FCI address)")
        numbers = {
            "move-speed": self.move_speed,
            "deadline": self.deadline,
            "collision-torque": self.collision_torque,
            "collision-force": self.collision_force,
        }
        for name, value in numbers.items():
            if not (math.isfinite(value) and value > 0):
                raise LolgpsError(f"--{name} must be positive and finite, got {value}")
        if self.collision_torque > 1.0:
            raise LolgpsError(
                f"--collision-torque is a fraction of the effort limits, at most 1, got "
                f"{self.collision_torque}"
            )


SIMULATED = RealArmConfig()  # rollouts in the simulator --sim names


class JointState(NamedTuple):
    """The arm's joints at one tick: angles (rad) and velocities (rad/s), ``[dof]`` each."""

    q: np.ndarray
    dq: np.ndarray


class LoopStats(NamedTuple):
    """The arm's loop so far: its seconds under torque command and moving, ticks under
    torque command and ticks it missed (a state read more than a tick after the last)."""

    torque_seconds: float
    move_seconds: float
    ticks: int
    missed: int


class ArmFaultError(Exception):
    """The arm's controller stopped a motion (a reflex, a communication fault, the learner
    late): one line saying why, and the joints where it stopped."""

    def __init__(self, reason: str, state: JointState) -> None:
        super().__init__(reason)
        self.reason, self.state = reason, state


class RealArm(Protocol):
    """What the learner asks of a torque-controlled arm (another arm implements these: a
    ros2_control effort interface, the KUKA FRI, a Kinova's low-level torque mode)."""

    def read_state(self) -> JointState:
        """The joints now (the arm at rest between motions)."""
        ...

    def command_torque(self, tau: np.ndarray, seconds: float) -> JointState:
        """Hold ``tau [dof]`` (N m, over the arm's own gravity compensation) for ``seconds``
        at the arm's own rate, starting the torque command if none runs, and return the
        joints at its end; a fault is an :class:`ArmFaultError`."""
        ...

    def stop(self) -> JointState:
        """End the torque command; the arm holds where it is."""
        ...

    def recover(self) -> None:
        """Clear the fault that stopped the arm (raises :class:`ArmFaultError` where it cannot)."""
        ...

    def move_to(self, q: np.ndarray, speed: float) -> JointState:
        """Move the joints to ``q`` in joint space, no joint faster than ``speed`` (rad/s),
        along a path that starts and ends at rest."""
        ...

    def stats(self) -> LoopStats:
        """The loop's seconds and ticks so far."""
        ...

    def close(self) -> None:
        """End any motion and let the arm go."""
        ...


def minimum_jerk(start: np.ndarray, goal: np.ndarray, speed: float) -> np.ndarray:
    """Joint positions ``[n, dof]``, one per tick, from ``start`` to ``goal`` along a
    minimum-jerk profile whose fastest joint peaks at ``speed`` (rad/s; the profile's peak
    is 15/8 of its mean speed): at rest, with zero acceleration, at both ends."""
    distance = float(np.abs(goal - start).max())
    ticks = max(2, math.ceil(1.875 * distance / speed / TICK))
    s = np.linspace(0.0, 1.0, ticks + 1)[1:, None]
    shape = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    return np.asarray(start + shape * (goal - start))


def _one_line(error: BaseException) -> str:
    """libfranka's message on one line, without its ``libfranka:`` prefix."""
    text = " ".join(str(error).split()) or type(error).__name__
    return text.removeprefix("libfranka: ")


class _Loop:
    """The arm's side of :class:`FrankaArm`, in its own process: requests from the learner
    on ``conn``, answered once each (module docstring)."""

    def __init__(self, conn: multiprocessing.connection.Connection, config: RealArmConfig,
                 effort: np.ndarray) -> None:  # fmt: skip
        import pylibfranka as franka

        self.franka, self.conn, self.config = franka, conn, config
        mode = franka.RealtimeConfig.kEnforce if config.realtime else franka.RealtimeConfig.kIgnore
        self.robot = franka.Robot(config.robot_ip, mode)
        torque = (config.collision_torque * effort).tolist()
        force = [config.collision_force] * 6
        self.robot.set_collision_behavior(torque, torque, force, force)
        self.control: Any = None  # the active torque command
        self.sent = np.zeros(len(effort))  # the torque last written, rate-limited
        self.held = 0  # ticks the last command was held past its period, waiting
        self.pending: str | None = None  # a fault to answer the next request with
        self.state = self._read()
        self.stats = [0.0, 0.0, 0, 0]

    def _read(self) -> JointState:
        robot_state = self.robot.read_once()
        return JointState(np.array(robot_state.q), np.array(robot_state.dq))

    def serve(self) -> None:
        """Answer requests until told to close or the learner is gone."""
        try:
            while True:
                request = self.conn.recv()
                if request[0] == "close":
                    self._end()
                    return
                answer = self._answer(request)
                if answer is not None:
                    self.conn.send(answer)
        except (EOFError, BrokenPipeError, ConnectionResetError):  # the learner is gone
            self._end()

    def _answer(self, request: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """The answer to ``request``; None where a torque request has answered itself."""
        kind = request[0]
        try:
            if self.pending is not None:
                reason, self.pending = self.pending, None
                return ("fault", reason, self.state, self._stats())
            if kind == "torque":
                self._torque(np.asarray(request[1]), round(request[2] / TICK))
                return None
            if kind == "stop":
                self._end()
            elif kind == "move":
                self._end()
                self._move(np.asarray(request[1]), request[2])
            elif kind == "recover":
                self.control = None
                self.robot.automatic_error_recovery()
                self.state = self._read()
            else:
                self.state = self._read()
        except (RuntimeError, self.franka.FrankaException) as error:
            self.control = None
            return ("fault", _one_line(error), self.state, self._stats())
        return ("state", self.state, self._stats())

    def _stats(self) -> LoopStats:
        torque, move, ticks, missed = self.stats
        return LoopStats(torque, move, int(ticks), int(missed))

    def _tick(self, tau: np.ndarray, finished: bool = False) -> None:
        """One tick of torque command: read the state, write ``tau`` rate-limited."""
        robot_state, period = self.control.readOnce()
        self.state = JointState(np.array(robot_state.q), np.array(robot_state.dq))
        self.stats[2] += 1
        self.stats[3] += max(round(period.to_sec() / TICK) - 1, 0)
        step = TORQUE_RATE * TICK
        self.sent = self.sent + np.clip(tau - self.sent, -step, step)
        command = self.franka.Torques(self.sent.tolist())
        command.motion_finished = finished
        self.control.writeOnce(command)

    def _torque(self, tau: np.ndarray, ticks: int) -> None:
        """Hold ``tau`` for ``ticks`` ticks and answer; then hold it until the next request
        or the deadline, past which the torque command ends and the next request is
        answered with the fault (as is a fault while holding)."""
        start = time.monotonic()
        if self.control is None:
            self.control = self.robot.start_torque_control()
            self.sent, self.held = np.zeros_like(tau), 0
        for _ in range(max(ticks - self.held, 1)):  # on the grid of the commands' periods
            self._tick(tau)
        self.held = 0
        self.conn.send(("state", self.state, self._stats()))
        waited = time.monotonic()
        try:
            while not self.conn.poll(0):
                late = time.monotonic() - waited
                if late > self.config.deadline:
                    self.pending = (
                        f"the learner's next command was over {late * 1000:.0f} ms late "
                        f"(deadline {self.config.deadline * 1000:.0f} ms): torque command ended"
                    )
                    self._end()
                    break
                self._tick(tau)
                self.held += 1
        except (RuntimeError, self.franka.FrankaException) as error:
            self.control = None
            self.pending = _one_line(error)
        self.stats[0] += time.monotonic() - start

    def _end(self) -> None:
        """End the torque command (the arm holds where it is), its torque brought down to
        zero over gravity at the rate libfranka allows."""
        if self.control is None:
            return
        try:
            while np.abs(self.sent).max() > 0.0:
                self._tick(np.zeros_like(self.sent))
            self._tick(self.sent, finished=True)
        finally:
            self.control = None

    def _move(self, goal: np.ndarray, speed: float) -> None:
        """A joint-space move to ``goal`` under the arm's joint impedance controller."""
        start = time.monotonic()
        franka = self.franka
        control = self.robot.start_joint_position_control(franka.ControllerMode.JointImpedance)
        robot_state, _ = control.readOnce()
        path = minimum_jerk(np.array(robot_state.q), goal, speed)
        path = np.concatenate([path, np.repeat(path[-1:], round(SETTLE / TICK), 0)])
        for i, q in enumerate(path):
            command = franka.JointPositions(q.tolist())
            command.motion_finished = i == len(path) - 1
            control.writeOnce(command)
            if not command.motion_finished:
                control.readOnce()
        self.stats[1] += time.monotonic() - start
        self.state = self._read()


def _serve(conn: multiprocessing.connection.Connection,
           learners: multiprocessing.connection.Connection, config: RealArmConfig,
           effort: np.ndarray) -> None:  # fmt: skip
    """The arm's process: connect, say so (or why not), then serve the learner on ``conn``.
    The learner's end, ``learners``, is closed here at once, so that the pipe ends when the
    learner is gone.  Ctrl-C is the learner's to handle: the loop ends its motion when the
    learner closes it or is gone."""
    learners.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        loop = _Loop(conn, config, effort)
    except Exception as error:  # noqa: BLE001 - any failure to connect, said in one line
        conn.send(("error", _one_line(error)))
        return
    conn.send(("state", loop.state, loop._stats()))
    loop.serve()


class FrankaArm:
    """:class:`RealArm` over libfranka, its 1 kHz loop in a process of its own (module
    docstring); ``effort [dof]`` the joints' torque limits (N m) the collision thresholds
    are a fraction of.  A :class:`LolgpsError` where the arm cannot be reached."""

    def __init__(self, config: RealArmConfig, effort: Sequence[float]) -> None:
        try:
            import pylibfranka  # noqa: F401 - checked here, used by the arm's process
        except ImportError:
            raise LolgpsError(
                f"--arm franka needs pylibfranka, which is not installed: {FRANKA_INSTALL}"
            ) from None
        self.config = config
        context = multiprocessing.get_context("fork")  # the loop's process imports no torch
        self._conn, theirs = context.Pipe()
        self._process = context.Process(
            target=_serve, args=(theirs, self._conn, config, np.asarray(effort)), daemon=True
        )
        self._process.start()
        theirs.close()
        self._stats = LoopStats(0.0, 0.0, 0, 0)
        answer = self._receive(ANSWER)
        if answer[0] == "error":
            self.close()
            raise LolgpsError(f"the Franka at {config.robot_ip} cannot be reached: {answer[1]}")
        self._state = self._unpack(answer)

    def _receive(self, seconds: float) -> tuple[Any, ...]:
        if not self._conn.poll(seconds):
            raise LolgpsError(
                f"the Franka at {self.config.robot_ip}: its control loop gave no answer in "
                f"{seconds:.0f} s"
            )
        try:
            answer: tuple[Any, ...] = self._conn.recv()
        except EOFError:
            raise LolgpsError(
                f"the Franka at {self.config.robot_ip}: its control loop ended"
            ) from None
        return answer

    def _unpack(self, answer: tuple[Any, ...]) -> JointState:
        """The joints an answer gives; a fault's is raised as :class:`ArmFaultError`."""
        self._stats = answer[-1]
        if answer[0] == "fault":
            raise ArmFaultError(answer[1], answer[2])
        state: JointState = answer[1]
        return state

    def _ask(self, *request: Any, seconds: float = 0.0) -> JointState:
        self._conn.send(request)
        return self._unpack(self._receive(seconds + ANSWER))

    def read_state(self) -> JointState:
        return self._ask("read")

    def command_torque(self, tau: np.ndarray, seconds: float) -> JointState:
        return self._ask("torque", np.asarray(tau, dtype=np.float64), seconds, seconds=seconds)

    def stop(self) -> JointState:
        return self._ask("stop")

    def recover(self) -> None:
        self._ask("recover")

    def move_to(self, q: np.ndarray, speed: float) -> JointState:
        state = self.read_state()
        seconds = 1.875 * float(np.abs(np.asarray(q) - state.q).max()) / speed + SETTLE
        # the arm's ticks, not the wall clock, pace the move: allow for a slow stand-in
        return self._ask("move", np.asarray(q, dtype=np.float64), speed, seconds=4 * seconds)

    def stats(self) -> LoopStats:
        return self._stats

    def close(self) -> None:
        if self._process.is_alive():
            with contextlib.suppress(OSError):  # the loop's process already gone
                self._conn.send(("close",))
            self._process.join(ANSWER)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._conn.close()
