"""Identification of the arm's parameters from simulated transitions."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch

from lolgps_torch.dynamics.identify import TorqueBalance, _solve, identify, objective, physical
from lolgps_torch.dynamics.parameters import ArmParameters, IdentifyConfig, identified_dynamics
from lolgps_torch.dynamics.transitions import Transitions
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.model import LINK_DAMPING, ControlStep, stabilising_inertia
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import Trajectories

FAR = (0.0, 2.0, -1.0)  # a hole out of the arm's way


@pytest.fixture(scope="module")
def arm() -> ArmSpec:
    return load_arm("robots/kuka_peg.urdf")


def _balance(arm: ArmSpec, config: WorldConfig) -> TorqueBalance:
    """The residual's setting for the world ``config``, each physics step driven by the command
    the world's model has act there (its known delay)."""
    plain = ArmDynamics(arm, config.gravity, "pybullet")
    dynamics = ArmDynamics(
        arm, config.gravity, "pybullet", None, stabilising_inertia(plain, config)
    )
    effort = torch.tensor(arm.effort, dtype=torch.float64)
    late = tuple(ControlStep(arm, config).late)
    return TorqueBalance(dynamics, effort, config.dt, LINK_DAMPING, config.substeps, late)


def _delayed(delay: float, plant: PlantConfig | None = None) -> tuple[WorldConfig, PlantConfig]:
    """A world whose state carries the actions a command delay of ``delay`` s needs (the
    delay known), and ``plant`` (default the nominal one) with its commands that late."""
    return WorldConfig(known_delay=delay), replace(plant or PlantConfig(), action_delay=delay)


def _rollouts(
    arm: ArmSpec, plant: PlantConfig, rollouts: int = 16, config: WorldConfig | None = None
) -> tuple[Transitions, list[float]]:
    """PD holds of random poses under sinusoidal pushes (scaled by each joint's inertia), the
    transitions clear of the joint limits, and the plant's link masses; in the world
    ``config`` (default :class:`WorldConfig`), whose state may carry past actions."""
    config = config or WorldConfig()
    # the pushes excite the arm past its speed limits at random poses: without the reflex
    world = PegWorld(arm, config, FAR, plant=replace(plant, limits="off"))
    rng = np.random.default_rng(0)
    lower, upper, n = np.asarray(arm.lower), np.asarray(arm.upper), arm.dof
    xs, us = [], []
    for _ in range(rollouts):
        ref = lower + (upper - lower) * rng.uniform(0.2, 0.8, n)
        M = ArmDynamics(arm).mass_matrix(torch.as_tensor(ref))
        m = 1.0 / torch.linalg.inv(M).diagonal().numpy()
        phase, freq = rng.uniform(0, 2 * np.pi, n), rng.uniform(2, 6, n)
        x, u = [world.reset(ref)], []
        for t in range(20):
            push = 3 * np.sin(freq * t * config.dt + phase)
            u.append(m * (9 * (ref - x[-1][:n]) - 6 * x[-1][n : 2 * n] + push))
            x.append(world.step(u[-1]))
        xs.append(np.stack(x))
        us.append(np.stack(u))
    masses = [
        pb.getDynamicsInfo(world.body, link, physicsClientId=world.client)[0]
        for link in range(pb.getNumJoints(world.body, physicsClientId=world.client))
    ]
    world.close()
    x_all = torch.as_tensor(np.stack(xs))
    q = x_all[..., :n]
    clear = ((q - torch.tensor(arm.lower)).amin(-1) > 0.05) & (
        (torch.tensor(arm.upper) - q).amin(-1) > 0.05
    )
    keep = clear[:, :-1] & clear[:, 1:]
    layout = config.layout(n)
    return Transitions.from_rollouts(x_all, torch.as_tensor(np.stack(us)), layout, keep), masses


@pytest.mark.parametrize("rollouts", [4, pytest.param(16, marks=pytest.mark.slow)])
def test_recovers_a_payload(arm: ArmSpec, rollouts: int) -> None:
    """1 kg on the peg, compensated by the URDF alone: identified within 5 %, and the
    compensation found to be the URDF's (ρ near 0), from 4 rollouts as from 16."""
    data, _ = _rollouts(arm, PlantConfig(payload=1.0, gravity_compensation="model"), rollouts)
    found = identify(_balance(arm, WorldConfig()), data, IdentifyConfig())
    assert float(found.payload) == pytest.approx(1.0, rel=0.05)
    assert float(found.compensation) == pytest.approx(1.0, abs=0.02)
    assert float(found.own) == pytest.approx(0.0, abs=0.1)


@pytest.mark.parametrize("rollouts", [4, pytest.param(6, marks=pytest.mark.slow)])
def test_recovers_a_payload_the_arm_compensates_itself(arm: ArmSpec, rollouts: int) -> None:
    """1 kg on the peg, compensated by the arm's own gravity (the plant's, payload included):
    its weight never shows, only its inertia, and it is still identified within 5 %, with the
    compensation found to be the arm's own (ρ near 1) from 4 or 6 rollouts."""
    data, _ = _rollouts(arm, PlantConfig(payload=1.0, gravity_compensation="plant"), rollouts)
    found = identify(_balance(arm, WorldConfig()), data, IdentifyConfig())
    assert float(found.payload) == pytest.approx(1.0, rel=0.05)
    assert float(found.own) == pytest.approx(1.0, abs=0.1)


@pytest.mark.slow
def test_the_compensations_share_stays_between_the_two_models(
    arm: ArmSpec, monkeypatch: pytest.MonkeyPatch
) -> None:
    """ρ mixes the URDF's compensation and the arm's own, so a fit ending outside [0, 1] is
    solved again with ρ held at the nearer end: with the prior's centre moved to ρ = 3 (and
    held there tightly) the free fit ends far beyond 1; held at 1, the arm compensating its
    own 1 kg payload is still identified within 5 %."""
    urdf = ArmParameters.urdf
    monkeypatch.setattr(
        ArmParameters,
        "urdf",
        staticmethod(lambda dynamics: replace(urdf(dynamics), own=torch.tensor(3.0))),
    )
    data, _ = _rollouts(arm, PlantConfig(payload=1.0, gravity_compensation="plant"), 6)
    found = identify(
        _balance(arm, WorldConfig()), data, IdentifyConfig(own_sd=0.01, noise_rounds=0)
    )
    assert float(found.own) == 1.0
    assert float(found.payload) == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize(
    ("residual", "within", "rollouts", "compensation"),
    [
        ("torque", 0.05, 8, "model"),
        pytest.param("speed", 0.2, 16, "model", marks=pytest.mark.slow),
        pytest.param("step", 0.05, 6, "model", marks=pytest.mark.slow),
        pytest.param("step", 0.05, 6, "plant", marks=pytest.mark.slow),
    ],
)
def test_recovers_link_masses(
    arm: ArmSpec, residual: str, within: float, rollouts: int, compensation: str
) -> None:
    """Link masses scaled by factors in [0.7, 1.3]: the elbow's and the wrist's bodies (links 3
    to 6, one link each) within 5 % by the torque balance and by the step residual (from 6
    rollouts: its Jacobian costs 5 forward dynamics per parameter), 20 % by the midpoint speed
    residual (its error of order dt^2 goes into the masses and the compensation's share). The base link's mass moves no
    actuated joint and link 2's hardly changes the torques of these rollouts: both stay near
    the prior. The same by the step residual where the arm compensates its own gravity, which
    the URDF's scaled (κ g_URDF) cannot equal link by link."""
    plant = PlantConfig(inertia_scale=0.3, seed=1, gravity_compensation=compensation)  # type: ignore[arg-type]
    data, masses = _rollouts(arm, plant, rollouts)
    balance = _balance(arm, WorldConfig())
    config = IdentifyConfig(residual=residual)  # type: ignore[arg-type]
    found = identified_dynamics(balance.dynamics, identify(balance, data, config))
    for body in range(2, 6):
        assert float(found.body.mass[body]) == pytest.approx(masses[body], rel=within)


@pytest.mark.slow
def test_sensor_noise_biases_the_torque_balance_not_the_speed_residuals(arm: ArmSpec) -> None:
    """With 1 mrad of sensor noise (10 mrad/s on the speeds) the measured accelerations carry
    the noise into the torque balance's regressors and its payload falls more than 10 % short;
    the speed and step residuals, whose regressors hold no measured acceleration, stay within
    5 %."""
    data, _ = _rollouts(
        arm, PlantConfig(payload=1.0, gravity_compensation="model", obs_noise=0.001)
    )
    balance = _balance(arm, WorldConfig())
    torque = identify(balance, data, IdentifyConfig(residual="torque"))
    assert float(torque.payload) < 0.9
    for residual in ("speed", "step"):
        found = identify(balance, data, IdentifyConfig(residual=residual))  # type: ignore[arg-type]
        assert float(found.payload) == pytest.approx(1.0, rel=0.05)


def test_the_step_residual_is_the_simulators_control_step(arm: ArmSpec) -> None:
    """On PyBullet's transitions of the arm as its URDF describes it, the step residual at the
    URDF's parameters is zero to rounding: it integrates the control step as the simulator
    does. The midpoint form leaves an error of order dt^2 (up to 0.1 rad/s here), which a fit
    absorbs into θ."""
    data, _ = _rollouts(arm, PlantConfig(), rollouts=4)
    balance = _balance(arm, WorldConfig())
    prior = ArmParameters.urdf(balance.dynamics)
    ones = torch.ones(arm.dof, dtype=torch.float64)
    step = balance.residual(prior, data, IdentifyConfig(residual="step"), ones)
    speed = balance.residual(prior, data, IdentifyConfig(residual="speed"), ones)
    assert float(step.abs().max()) < 1e-8
    assert float(speed.abs().max()) > 1e-3


@pytest.mark.parametrize("delay", [0.02, 0.05])
def test_the_step_residual_is_the_simulators_control_step_under_a_delay(
    arm: ArmSpec, delay: float
) -> None:
    """With commands 20 ms late (2 of the 5 physics steps driven by the previous command) or
    50 ms late (a whole control step), the step residual at the URDF's parameters is zero to
    rounding on PyBullet's transitions: it drives each physics step with the command acting
    there, taken from the state's action history. Holding u_t over the step instead leaves
    errors of up to 0.13 and 0.33 rad/s."""
    config, plant = _delayed(delay)
    data, _ = _rollouts(arm, plant, rollouts=4, config=config)
    assert data.commands.shape[1:] == (2, arm.dof)
    balance = _balance(arm, config)
    prior = ArmParameters.urdf(balance.dynamics)
    ones = torch.ones(arm.dof, dtype=torch.float64)
    step = balance.residual(prior, data, IdentifyConfig(residual="step"), ones)
    undelayed = balance._replace(late=()).residual(
        prior, data, IdentifyConfig(residual="step"), ones
    )
    assert float(step.abs().max()) < 1e-8
    assert float(undelayed.abs().max()) > 1e-2


@pytest.mark.slow  # the step residual under a delay by default: its test above
@pytest.mark.parametrize("delay", [0.02, 0.05])
def test_recovers_a_payload_under_a_delay(arm: ArmSpec, delay: float) -> None:
    """1 kg on the peg, compensated by the URDF alone, its commands 20 or 50 ms late (the delay
    known): identified within 5 % from 6 rollouts, κ within 0.02."""
    config, plant = _delayed(delay, PlantConfig(payload=1.0, gravity_compensation="model"))
    data, _ = _rollouts(arm, plant, rollouts=6, config=config)
    found = identify(_balance(arm, config), data, IdentifyConfig(noise_rounds=0))
    assert float(found.payload) == pytest.approx(1.0, rel=0.05)
    assert float(found.compensation) == pytest.approx(1.0, abs=0.02)


def test_a_delay_needs_the_past_commands(arm: ArmSpec) -> None:
    """Transitions without the past commands a delay makes act are refused, not fitted as
    though u_t drove the whole step."""
    data, _ = _rollouts(arm, PlantConfig(), rollouts=1)
    balance = _balance(arm, WorldConfig(known_delay=0.02))
    prior = ArmParameters.urdf(balance.dynamics)
    ones = torch.ones(arm.dof, dtype=torch.float64)
    with pytest.raises(LolgpsError, match="past commands"):
        balance.residual(prior, data, IdentifyConfig(), ones)


@pytest.mark.slow
def test_the_step_residual_starts_from_the_torque_balances_estimate(arm: ArmSpec) -> None:
    """On the KUKA carrying 1 kg (6 rollouts), under least squares (Huber's threshold out of
    reach), the step residual's Levenberg-Marquardt started from the midpoint form's estimate
    stalls in a local minimum with a negative payload, its objective over a hundred times the
    minimum's; started from the torque balance's estimate (what :func:`identify` does) it finds
    the payload within 2 %."""
    data, _ = _rollouts(arm, PlantConfig(payload=1.0, gravity_compensation="model"), rollouts=6)
    balance = _balance(arm, WorldConfig())
    prior = ArmParameters.urdf(balance.dynamics)
    config = IdentifyConfig(noise_rounds=0, outlier=1e9)

    def stacked(theta: torch.Tensor) -> torch.Tensor:
        return objective(balance, prior, data, config, theta)

    midpoint = identify(balance, data, replace(config, residual="speed"))
    stalled = _solve(stacked, midpoint.flat(), config)
    found = identify(balance, data, config)
    assert float(prior.unflat(stalled).payload) < 0
    assert float(stacked(found.flat()).square().sum()) < 1e-2 * float(
        stacked(stalled).square().sum()
    )
    assert float(found.payload) == pytest.approx(1.0, rel=0.02)


def test_objective_gradients(arm: ArmSpec) -> None:
    """The MAP objective's derivative in θ against finite differences (gradcheck)."""
    balance = _balance(arm, WorldConfig())
    rng = np.random.default_rng(2)
    n = arm.dof
    q = torch.as_tensor(np.asarray(arm.lower) * 0.4 + np.asarray(arm.upper) * 0.6)
    q0, qd0, u, q1, qd1 = (
        q + torch.as_tensor(rng.normal(0, s, (3, n))) for s in (0.05, 0.5, 2.0, 0.05, 0.5)
    )
    data = Transitions(q0, qd0, u[:, None], q1, qd1)
    prior = ArmParameters.urdf(balance.dynamics)
    theta = prior.flat() + torch.as_tensor(rng.normal(0, 0.1, prior.flat().shape))
    config = IdentifyConfig(friction_speed=1.0)

    def loss(t: torch.Tensor) -> torch.Tensor:
        return objective(balance, prior, data, config, t).square().sum()

    assert torch.autograd.gradcheck(loss, (theta.requires_grad_(),))


def test_the_learner_reports_the_identified_arm_on_unseen_rollouts() -> None:
    """With ``identify``, a condition's learner identifies the arm from the earlier conditions'
    free-space transitions and reports it once, with the one-step errors on its own first
    rollouts: on an arm carrying 1 kg that its URDF lacks (compensated by the URDF), the
    identified payload is near 1 kg and its one-step error a fraction of the URDF model's."""
    from lolgps_torch.data.records import IdentifiedRecord
    from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate

    plant = PlantConfig(payload=1.0, gravity_compensation="model", limits="off")
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf", plant=plant), n_worlds=5)
    config = LocalConfig(identify=True, model_plans=0)  # from the hold: no plan needed
    reports: list[IdentifiedRecord] = []
    try:
        first = LocalLearner(task, (0.02, 0.02), config, 0, reports.append, 0)
        for i in range(2):
            iterate(first, first.p_cur, None, False, (0, i, 0.0))
        assert reports == []  # nothing to identify from before the first condition
        second = LocalLearner(task, (-0.02, 0.02), config, 1, reports.append, 1)
        iterate(second, second.p_cur, None, False, (1, 0, 0.0))  # reported from its samples
    finally:
        task.close()
    (report,) = reports
    assert report.condition == 1 and report.transitions > 0
    assert report.payload == pytest.approx(1.0, rel=0.25)
    assert report.error_identified < 0.2 * report.error_urdf
    assert report.error_plant < 1e-8  # the simulated arm's own model: exact without noise
    assert report.to_json()["event"] == "identified"


def _which_free(T: int, edit: Callable[[torch.Tensor, PegTask], None]) -> list[list[bool]]:
    """:func:`~lolgps_torch.dynamics.transitions.free_transitions` of three KUKA rollouts of T steps at rest at its start
    pose, the tip 5 cm above the table and the peg pointing down, as ``edit(x, task)`` leaves
    their states ``x [3, T+1, dX]``."""
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=1)
    try:
        lay = task.layout
        x = torch.zeros(3, T + 1, lay.dX, dtype=torch.float64)
        x[..., lay.q] = task.q0
        high = task.config.world.depth + 0.05
        x[..., lay.points.start + 2] = high
        x[..., lay.points.start + 5] = high  # the top's offset as the tip's: pointing down
        edit(x, task)
        zeros = torch.zeros(3, T, dtype=torch.float64)
        u = torch.zeros(3, T, lay.dU, dtype=torch.float64)
        samples = Trajectories(
            x[:, :-1], u, zeros, zeros[:, 0], zeros[:, 0] > 0, x[:, -1], zeros[:, 0] > 0
        )
        return task.transitions.free(samples)[1].tolist()
    finally:
        task.close()


def test_a_peg_lying_on_the_table_is_not_free() -> None:
    """A transition counts as free of contact only with the tip above the table by the
    clearance and the peg pointing down: tilted up, its far end reaches lower than the tip."""

    def edit(x: torch.Tensor, task: PegTask) -> None:
        points = task.layout.points.start
        x[1, ..., points + 5] -= 0.16  # the top 1 cm below the tip (0.15 m above its target)
        x[2, ..., points + 2] = task.config.world.depth + 0.01  # the tip too low

    assert _which_free(2, edit) == [[True, True], [False, False], [False, False]]


def test_a_joint_that_can_strike_its_limit_within_the_step_is_not_free() -> None:
    """A joint 0.08 rad short of its limit is free at rest, not at 17 rad/s either way (it can
    go 0.85 rad in the control step)."""

    def edit(x: torch.Tensor, task: PegTask) -> None:
        q, qd = task.layout.q, task.layout.qd
        x[..., q.start + 3] = task.arm.upper[3] - 0.08
        x[1, 0, qd.start + 3] = 17.0  # toward the limit
        x[2, 1, qd.start + 3] = -17.0  # back from it at the end

    assert _which_free(1, edit) == [[True], [False], [False]]


def test_an_arm_that_cannot_exist_is_not_identified(arm: ArmSpec) -> None:
    """A body of negative mass is not physical; the URDF's arm is."""
    balance = _balance(arm, WorldConfig())
    prior = ArmParameters.urdf(balance.dynamics)
    assert physical(balance.dynamics, prior)
    scale = prior.mass_scale.clone()
    scale[3] = -0.5
    assert not physical(balance.dynamics, replace(prior, mass_scale=scale))


def test_a_failed_identification_keeps_the_model(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where no arm that can exist fits the transitions, the task warns and keeps its model."""
    import lolgps_torch.dynamics.identify as identify_module
    from lolgps_torch.errors import NumericalError

    def fails(*_: object) -> ArmParameters:
        raise NumericalError("no arm")

    monkeypatch.setattr(identify_module, "identify", fails)
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=1)
    try:
        data, _ = _rollouts(task.arm, PlantConfig(), rollouts=1)
        task.transitions.kept = data
        model = task.model
        with pytest.warns(UserWarning, match="could not be identified"):
            assert task.identify_model(IdentifyConfig()) is None
        assert task.model is model
    finally:
        task.close()


@pytest.mark.slow
def test_an_identification_worse_than_the_model_it_would_replace_is_not_taken(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An identified arm that explains the transitions worse than the task's model (here a
    7 kg payload on the URDF's own arm) is refused with a warning; the next identification
    starts from the arm identified before."""
    import lolgps_torch.dynamics.identify as identify_module

    starts: list[ArmParameters | None] = []

    def heavy(
        balance: TorqueBalance, data: Transitions, config: IdentifyConfig, start: object
    ) -> ArmParameters:
        starts.append(start)  # type: ignore[arg-type]
        prior = ArmParameters.urdf(balance.dynamics)
        return replace(prior, payload=torch.tensor(7.0, dtype=torch.float64))

    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=1)
    try:
        data, _ = _rollouts(task.arm, PlantConfig(), rollouts=1)
        task.transitions.kept = data
        model = task.model
        monkeypatch.setattr(identify_module, "identify", heavy)
        with pytest.warns(UserWarning, match="worse than the model it would replace"):
            assert task.identify_model(IdentifyConfig(noise_rounds=0)) is None
        assert task.model is model
        monkeypatch.setattr(identify_module, "identify", identify)
        found = task.identify_model(IdentifyConfig(noise_rounds=0))
        assert found is not None and task.model is not model
        monkeypatch.setattr(identify_module, "identify", heavy)
        with pytest.warns(UserWarning, match="worse than the model it would replace"):
            task.identify_model(IdentifyConfig(noise_rounds=0))
        assert starts == [None, found]
    finally:
        task.close()


@pytest.mark.slow
def test_a_transition_the_model_does_not_describe_pulls_the_fit_by_little(arm: ArmSpec) -> None:
    """One transition in which a joint strikes its limit and rebounds (its end speed a third of
    its start speed, reversed) among the KUKA's, carrying 1 kg (3 rollouts): least squares
    (Huber's threshold out of reach; converged within 10 steps) scales a link's mass by a factor
    15 % or more away from 1; Huber's loss keeps every link's within 5 % and the payload within
    2 %."""
    data, _ = _rollouts(arm, PlantConfig(payload=1.0, gravity_compensation="model"), rollouts=3)
    struck = data.qd1.clone()
    fastest = int(data.qd0[:, 1].abs().argmax())
    struck[fastest, 1] = -data.qd0[fastest, 1] / 3
    data = data._replace(qd1=struck)
    balance = _balance(arm, WorldConfig())
    squares = identify(balance, data, IdentifyConfig(outlier=1e9, noise_rounds=0, iterations=10))
    huber = identify(balance, data, IdentifyConfig(noise_rounds=0))
    assert float((squares.mass_scale - 1.0).abs().max()) > 0.15
    assert float((huber.mass_scale - 1.0).abs().max()) < 0.05
    assert float(huber.payload) == pytest.approx(1.0, rel=0.02)
