"""A stand-in Franka for tests/test_franka.py: franky-sim's MuJoCo FR3 serving the libfranka
protocol on 127.0.0.1, in the network namespace this runs in (``unshare -n``), while a
command runs (told the server's process id in ``FRANKA_STAND_IN_PID``); the server is
stopped when the command ends, however it ends.

    unshare -n -- python tests/franka_stand_in.py [--reflexes] -- COMMAND ...

franky-sim has no reflexes of its own.  With ``--reflexes`` the server does what a real arm's
controller does to a torque command: a joint faster than the FR3's velocity limit aborts the
motion with ``joint_velocity_violation``, and no command for :data:`QUIET_TICKS` ticks with
``communication_constraints_violation`` (the robot enforcing the protocol's timing).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from typing import Any

import numpy as np
from franky_sim import SimulationServer
from franky_sim.franka_robot_protocol import (
    BaseCommand,
    MoveCommandControllerMode,
    MoveStatus,
    RobotCommand,
)
from franky_sim.franka_robot_server import FrankaRobotServer
from franky_sim.mujoco_simulator import MujocoSimulator

QUIET_TICKS = 30  # ticks without a command that end a torque command (the protocol's timing)
# the FR3's joint velocity limits (rad/s), from its datasheet
VELOCITY = (2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26)
# indices of libfranka's error flags
JOINT_VELOCITY_VIOLATION = 3
COMMUNICATION_CONSTRAINTS_VIOLATION = 31
HOST = "127.0.0.1"


class ReflexServer(FrankaRobotServer):  # type: ignore[misc]
    """franky-sim's server with a velocity reflex and the protocol's timing enforced (when
    :attr:`reflexes`)."""

    reflexes = False

    def __init__(self, robot: Any, hosts: list[str]) -> None:
        super().__init__(robot, hosts)
        self.torque, self.quiet, self.error, self.aborted = False, 0, -1, 0

    def start_motion(self, controller: Any, generator: Any, motion: int) -> None:
        super().start_motion(controller, generator, motion)
        self.torque = controller == MoveCommandControllerMode.kExternalController
        self.quiet = 0

    def stop_motion(self, send_preemption_signal: bool = True) -> None:
        super().stop_motion(send_preemption_signal)
        self.torque = False

    def _handle_udp_command(self, command_data: bytes) -> None:
        self.quiet = 0
        super()._handle_udp_command(command_data)

    def _post_process_commands(self) -> None:
        super()._post_process_commands()
        if self.aborted:  # the state saying why has gone out: abort the motion
            BaseCommand.send_response(
                self._tcp_socket, RobotCommand.kMove, self.aborted, MoveStatus.kReflexAborted
            )
            self.aborted = 0
        if not (self.reflexes and self.torque and self.current_motion_id):
            return
        self.quiet += 1
        if (np.abs(self.robot.inner_state.dq) > np.array(VELOCITY)).any():
            self._abort(JOINT_VELOCITY_VIOLATION)
        elif self.quiet > QUIET_TICKS:
            self._abort(COMMUNICATION_CONSTRAINTS_VIOLATION)

    def _abort(self, error: int) -> None:
        """Stop the motion, the state saying ``error``; the motion's answer follows it."""
        self.aborted = self.current_motion_id
        self.stop_motion(send_preemption_signal=False)
        self.reset_current_motion_id()
        self.error = error

    @property
    def robot_state(self) -> Any:
        state = super().robot_state
        if self.error < 0:
            return state
        flags = tuple(i == self.error for i in range(len(state.reflex_reason)))
        if self.aborted:
            return state.replace(errors=flags, reflex_reason=flags)
        return state.replace(reflex_reason=flags)  # libfranka's last_motion_errors


class Server(SimulationServer):  # type: ignore[misc]
    """franky-sim's simulation server with a :class:`ReflexServer` per robot."""

    def init(self) -> None:
        for robot in self.sim.robots:
            server = ReflexServer(robot, [HOST])
            server.init()
            self.robot_servers.append(server)
        self.sim.start()


def serve(reflexes: bool) -> None:
    """Run the server until killed, saying ``ready`` once it listens."""
    ReflexServer.reflexes = reflexes
    with MujocoSimulator(enable_visualization=False) as sim:
        sim.add_robot()
        with Server(sim, [HOST]) as server:
            print("ready", flush=True)
            server.run_forever()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--reflexes", action="store_true")
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    if args.serve:
        serve(args.reflexes)
        return 0
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    flags = ["--reflexes"] if args.reflexes else []
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve", *flags], stdout=subprocess.PIPE, text=True
    )
    try:
        assert server.stdout is not None
        if server.stdout.readline().strip() != "ready":
            print("the stand-in server did not start", file=sys.stderr)
            return 3
        command = args.command[1:] if args.command[:1] == ["--"] else args.command
        environment = {**os.environ, "FRANKA_STAND_IN_PID": str(server.pid)}
        return subprocess.run(command, env=environment).returncode
    finally:
        server.terminate()
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


if __name__ == "__main__":
    sys.exit(main())
