"""What sensor noise does to the arm's identification, on the stream's own first rollouts.

    python scripts/research/identify_noise.py [--urdf URDF] [--payload KG]
        [--obs-noise 0 0.001] [--noise-rounds 0 1] [--residual torque speed] [--iterations 3]
        [--action-delay SECONDS [--detect-delay]] [--gravity-compensation plant] [--seed S]
        [--plant-inertia-scale S --plant-seed K]

For each sensor noise (rad; the joint velocities get 10 times as much) the arm carries
``--payload`` kg that its URDF lacks, compensated by the URDF's gravity alone
(``--gravity-compensation model``, the default here) or by its own, payload included
(``plant``, the stream's default). A condition's learner (the nominal hole) samples
``--iterations`` batches of its first controller, planned on the arm's model, as the stream's
first condition does; their free-space transitions identify the arm
(:func:`lolgps_torch.dynamics.identify.identify`) once per ``--residual`` and
``--noise-rounds`` value (``IdentifyConfig.residual``, ``IdentifyConfig.noise_rounds``).
Each line gives the identified payload, the gravity compensation's gain κ and its own-gravity
share ρ (truth: the payload, 1, and 0 for ``model`` or 1 for ``plant``) and the one-step joint-speed error (rad/s) of
the identified model, of the URDF's and of the simulated arm's own
(:meth:`lolgps_torch.task.PegTask.plant_model`) on a second condition's first rollouts (a hole
0.04 m away), which the identification has not seen, and the identification's wall time. With
``--plant-inertia-scale`` every link's mass and inertia are scaled too (``PlantConfig``), and
each line also gives the mass of the last moving body, the links after the last joint with the
payload, as identified and as simulated (kg): what the transitions fix where the payload and
those links' scales can trade.

With ``--action-delay`` the arm's commands act that late, and the learner allows for that
delay as the stream's ``--known-delay`` makes it (:func:`lolgps_torch.commands.probes.allow_for_delay`: the
state carries the last actions, and from half a control step on the first controller is the
hold rather than one planned on the model); with ``--detect-delay``, for the delay the stream
estimates instead (:func:`lolgps_torch.commands.probes.detect_delay`, none where it finds none).

Noise on the observed joint velocities enters the torque balance through the accelerations
``(qd_1 - qd_0) / dt`` that multiply the inertial parameters: an error in the regressors,
which biases least squares whatever the weighting.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from lolgps_torch.arm_probes import probe_world
from lolgps_torch.cli import run
from lolgps_torch.commands.probes import allow_for_delay, detect_delay
from lolgps_torch.dynamics.parameters import ArmParameters, IdentifyConfig, identified_dynamics
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.world import PegWorld
from lolgps_torch.task import PegTask, TaskConfig


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--payload", type=float, default=1.0, help="kg")
    parser.add_argument("--obs-noise", type=float, nargs="+", default=[0.0, 0.001])
    parser.add_argument("--noise-rounds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--residual", nargs="+", default=["torque", "speed", "step"])
    parser.add_argument("--iterations", type=int, default=3, help="batches to identify from")
    parser.add_argument(
        "--action-delay", type=float, default=0.0, help="s between a command and its action"
    )
    parser.add_argument(
        "--detect-delay",
        action="store_true",
        help="allow for the delay the stream estimates, not the true one",
    )
    parser.add_argument(
        "--gravity-compensation", choices=("model", "plant"), default="model",
        help="the arm compensated by the URDF's gravity or by its own (%(default)s)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plant-inertia-scale", type=float, default=0.0, help="S, links × [1±S]")
    parser.add_argument("--plant-seed", type=int, default=0, help="the links' factors' seed")
    return parser.parse_args()


def last_body_masses(task: PegTask, found: ArmParameters) -> tuple[float, float]:
    """The last moving body's mass (kg), payload included, as identified and as simulated."""
    urdf = ControlStep(task.arm, task.config.world, task.device).urdf
    with probe_world(task.config) as (world, _):
        assert isinstance(world, PegWorld)
        simulated = replace(task.arm, urdf_text=world.plant_urdf())
    true = ControlStep(simulated, task.config.world, task.device).urdf
    return float(identified_dynamics(urdf, found).body.mass[-1]), float(true.body.mass[-1])


def main() -> None:
    args = parse_args()
    print(
        "| sensor noise (rad) | delay allowed for (s) | residual | noise rounds | payload (kg) | κ | ρ | one-step error: identified / URDF / simulated arm's own (rad/s) | last body, identified / simulated (kg) | identification (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise in args.obs_noise:
        plant = PlantConfig(
            payload=args.payload,
            gravity_compensation=args.gravity_compensation,
            obs_noise=noise,
            action_delay=args.action_delay,
            inertia_scale=args.plant_inertia_scale,
            seed=args.plant_seed,
        )
        task_config = TaskConfig(urdf=args.urdf, plant=plant)
        config = LocalConfig(identify=True)
        delay = detect_delay(task_config, True) if args.detect_delay else args.action_delay
        if delay > 0.0:
            task_config, config = allow_for_delay(task_config, config, delay)
        task = PegTask(task_config, n_worlds=5)
        try:
            first = LocalLearner(task, (0.0, 0.0), config, args.seed)
            for _ in range(args.iterations):
                first.sample(first.p_cur)  # recorded for the identification
            held_out = LocalLearner(
                task, (0.04, 0.0), replace(config, identify=False), args.seed + 1
            )
            unseen = held_out.sample(held_out.p_cur)
            for residual in args.residual:
                for rounds in args.noise_rounds:
                    setting = IdentifyConfig(noise_rounds=rounds, residual=residual)
                    start = time.perf_counter()
                    found = task.identify_model(setting)
                    seconds = time.perf_counter() - start
                    if found is None:  # explains the transitions worse than the model in use
                        print(
                            f"| {noise:g} | {delay:g} | {residual} | {rounds} | kept the model "
                            f"identified before | | | | | {seconds:.1f} |"
                        )
                        continue
                    identified, urdf, own, _ = task.one_step_errors(unseen)
                    mass, true_mass = last_body_masses(task, found)
                    print(
                        f"| {noise:g} | {delay:g} | {residual} | {rounds} | {float(found.payload):.3f} | "
                        f"{float(found.compensation):.3f} | {float(found.own):.2f} | "
                        f"{identified:.4f} / {urdf:.4f} / {own:.4f} | "
                        f"{mass:.3f} / {true_mass:.3f} | {seconds:.1f} |"
                    )
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
