"""The global policy ``pi_theta(u | x) = N(mu_theta(x), diag(sigma^2))`` (docs/ALGORITHM.md section 7).

Layout: states ``[..., dX]`` map to action means ``[..., dU]``; any leading dimensions (samples,
time) pass through. Parameters and buffers are float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Literal, NamedTuple, get_args

import torch
from torch import Tensor
from torch.nn import functional

from lolgps_torch.errors import LolgpsError, check_fields
from lolgps_torch.policy.guard import Guard

AdamDtype = Literal["float32", "float64"]


@dataclass(frozen=True)
class PolicyConfig:
    """Global policy and S-step (paper section 4; docs/ALGORITHM.md sections 7 and 10).

    :param hidden_sizes: widths of the ReLU hidden layers (paper: 5 layers, 42 units each, i.e.
        input -> 4 x 42 ReLU -> dU).
    :param learning_rate: Adam step size (original GPS: 1e-3).
    :param batch_size: rows per Adam minibatch. 256 about halves the S-step's time against
        512, with the same positions reached over 26 runs on 11 arms (docs/HISTORY.md [R23]).
    :param steps: Adam steps per S-step (the original GPS: 4000 steps of 25). With 500 the
        Panda's seed-2 stream kept 6/8 positions (docs/HISTORY.md [R12]).
    :param std_floor: lower bound on the whitening standard deviation, so constant state
        dimensions (zero variance) do not divide by zero.
    :param seed: seed of the weight initialisation and of the S-step's minibatch draws.
    :param pre_weight: weight lambda of KL(pi || p_pre) in the S-step loss (paper eq. 8: 1).
    :param num_threads: torch intra-op threads during the S-step's Adam loop (None: leave
        torch's setting). Its matrices are too small to gain from threads, and on busy cores
        each parallel region waits for a descheduled thread: with 2 threads on 2 loaded cores a
        step took ~20x longer than with 1.
    :param feedback: the gain head, ``mu = a(h) + B(h) z`` (off: the plain MLP ``a(h)``).
    :param guard: bound the acting policy by its data (:mod:`lolgps_torch.policy.guard`): a
        brake taking ``guard_brake`` of the joint speeds away per step while a joint passes
        ``guard_speed`` times the largest speed in D_g or the tip retreats (``guard_retreat``),
        and, with ``guard_torque``, torques within that many times the largest teacher torque
        per joint.
    :param guard_torque: the torque bound, in largest teacher torques (None: unbounded). On
        12 KUKA seeds a bound of 1.3 cost area 6 up to 36 points and kept the brake from
        stopping a flung arm (docs/HISTORY.md, "the guard").
    :param guard_speed: the speed that trips the brake, in D_g's largest speeds from
        ``guard_window`` steps before on. Below 3 the policy's first steps towards far holes
        trip it (12 KUKA seeds; docs/HISTORY.md, "the guard").
    :param guard_window: steps before a step from which on D_g's largest speed sets that
        step's trip speed (None: the largest over every step). With 3, the arm is stopped
        where it is flung from the plate, late in the rollout, where its teachers were slow
        (8 KUKA seeds: farthest test miss 1.46 against 0.36 m, average final success 0.964
        against 0.965; docs/HISTORY.md, "the guard").
    :param guard_brake: the brake's share of the joint speeds taken away per control step.
    :param guard_retreat: the brake also acts while the tip is farther than this (m) beyond
        its closest approach to the target in the rollout, on top of the largest such retreat
        in D_g (None: no retreat trips it). With 0.05 and the brake acting only while a bound
        is passed, no test rollout on 12 KUKA seeds ended beyond 0.3 m from its hole
        (docs/HISTORY.md, "the guard").
    :param guard_hover: where the tip's retreat trips the brake while the peg is higher than
        this (m) above the hole's mouth, the brake steers it to that height above its hole,
        moving both points there at ``1 / guard_hover_time`` of their distance per second,
        until the tip is within 0.02 m of that point, instead of stopping the arm where it is
        (None, ``--guard-hover none``: it stops it). On 12 KUKA seeds every test rollout of
        the final policy then ended within 0.16 m of its hole (0.42 m with None; docs/HISTORY.md,
        "the hover").
    :param guard_hover_time: the time constant (s) of that approach.
    :param guard_limit: the brake also trips where a joint passes this share of its velocity
        limit, before the arm's own controller would stop the arm there; and every action, the
        policy's and the local controllers' samples' (:meth:`limits`), is scaled down where the
        arm's model predicts that a joint would pass it within the step
        (:func:`~lolgps_torch.policy.guard.within_limits`).
    :param guard_position: that scaling also keeps each bounded joint this far (rad) inside
        its position limits.
    :param adam_dtype: floating type of the S-step's Adam loop (net copy, whitened states,
        scaled targets); the policy itself stays float64. float32 takes a third less loop
        time and reached as many positions over 38 paired runs, but fewer on the published
        Panda (59 against 63 of 72) with more repair rounds (docs/HISTORY.md [R12.1]
        [R19]), so float64 stays the default.
    """

    hidden_sizes: tuple[int, ...] = (42, 42, 42, 42)
    learning_rate: float = 3e-3
    batch_size: int = 256
    steps: int = 1000
    std_floor: float = 1e-3
    seed: int = 0
    pre_weight: float = 0.1
    num_threads: int | None = 1
    feedback: bool = True
    adam_dtype: AdamDtype = "float64"
    guard: bool = True
    guard_torque: float | None = None
    guard_speed: float = 3.0
    guard_window: int | None = 3
    guard_brake: float = 0.5
    guard_retreat: float | None = 0.05
    guard_hover: float | None = 0.05
    guard_hover_time: float = 1.0
    guard_limit: float = 0.8
    guard_position: float = 0.1

    def limits(self) -> tuple[float, float] | None:
        """``(guard_limit, guard_position)``: the share of the velocity limits and the margin
        (rad) inside the position limits within which every motion is kept, the policy's and
        the local controllers' samples alike; None with the guard off."""
        return (self.guard_limit, self.guard_position) if self.guard else None

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "hidden_sizes": len(self.hidden_sizes) >= 1 and min(self.hidden_sizes) >= 1,
                "learning_rate": 0.0 < self.learning_rate < math.inf,
                "batch_size": self.batch_size >= 1,
                "steps": self.steps >= 1,
                "std_floor": 0.0 < self.std_floor < math.inf,
                "seed": self.seed >= 0,
                "pre_weight": 0.0 <= self.pre_weight < math.inf,
                "num_threads": self.num_threads is None or self.num_threads >= 1,
                "adam_dtype": self.adam_dtype in get_args(AdamDtype),
                "guard_torque": self.guard_torque is None or 0.0 < self.guard_torque < math.inf,
                "guard_speed": 0.0 < self.guard_speed < math.inf,
                "guard_window": self.guard_window is None or self.guard_window >= 0,
                "guard_brake": 0.0 < self.guard_brake <= 1.0,
                "guard_retreat": self.guard_retreat is None or 0.0 <= self.guard_retreat < math.inf,
                "guard_hover": self.guard_hover is None or 0.0 <= self.guard_hover < math.inf,
                "guard_hover_time": 0.0 < self.guard_hover_time < math.inf,
                "guard_limit": 0.0 < self.guard_limit <= 1.0,
                "guard_position": 0.0 <= self.guard_position < math.inf,
            },
        )


def _mlp(
    dX: int, dU: int, hidden_sizes: tuple[int, ...], generator: torch.Generator
) -> torch.nn.Sequential:
    """``dX -> hidden (ReLU) ... -> dU`` in float64, with torch's default ``Linear`` initialisation
    (weights ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``, biases alike) drawn from ``generator``."""
    sizes = (dX, *hidden_sizes, dU)
    layers: list[torch.nn.Module] = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
        linear = torch.nn.Linear(fan_in, fan_out, dtype=torch.float64)
        bound = 1.0 / math.sqrt(fan_in)
        with torch.no_grad():
            linear.weight.uniform_(-bound, bound, generator=generator)
            linear.bias.uniform_(-bound, bound, generator=generator)
        layers += [linear, torch.nn.ReLU()]
    return torch.nn.Sequential(*layers[:-1])


Product = Callable[[Tensor, Tensor], Tensor]  # (x, W) -> x W^T


class Layer(NamedTuple):
    """A linear layer's weight ``W [out, in]`` and bias ``b [out]``: ``h -> h W^T + b``."""

    weight: Tensor
    bias: Tensor

    def __call__(self, h: Tensor, product: Product | None) -> Tensor:
        """``h W^T + b`` (``product(h, W)`` in place of ``h W^T``; None: torch's)."""
        if product is None:
            return functional.linear(h, self.weight, self.bias)
        return product(h, self.weight) + self.bias


Step = Layer | torch.nn.Module  # a linear layer's weights, or a module without weights


def _apply(steps: tuple[Step, ...], h: Tensor, product: Product | None) -> Tensor:
    """``steps`` applied to ``h`` in turn; a ReLU as ``h.relu()``, another module called."""
    for step in steps:
        if isinstance(step, Layer):
            h = step(h, product)
        elif isinstance(step, torch.nn.ReLU):
            h = h.relu()
        else:
            h = step(h)
    return h


class Net(NamedTuple):
    """The policy's net with its linear layers as plain tensors, the modules' own (autograd
    and in-place updates of the weights reach them): the MLP's ``layers`` in order, and the
    gain head ``gain`` (None: the plain MLP). Taken out of the modules once, it evaluates
    without the module calls and attribute look-ups, which took most of a one-row evaluation
    (every control step of a policy rollout)."""

    layers: tuple[Step, ...]
    gain: Layer | None

    def __call__(self, z: Tensor, product: Product | None = None) -> Tensor:
        """The net's output at whitened states ``z: [..., dX]``, before the output scaling:
        ``a(h) + B(h) z`` with the gain head, else ``a(h)``, where ``h`` is the output of all
        layers but the last, ``a`` the last layer and ``B(h)`` the gain head's output as
        ``[..., dU, dX]``; ``product(h, W)`` in place of each ``h W^T`` (None: torch's)."""
        if self.gain is None:
            return _apply(self.layers, z, product)
        h = _apply(self.layers[:-1], z, product)
        gain = self.gain(h, product)
        out = _apply(self.layers[-1:], h, product)
        return out + (gain.unflatten(-1, (out.shape[-1], z.shape[-1])) * z.unsqueeze(-2)).sum(-1)


class Acting(NamedTuple):
    """``mu_theta`` as plain tensors (:meth:`GaussianPolicy.acting`): the whitening, the
    :class:`Net` and the output scaling."""

    x_mean: Tensor
    x_std: Tensor
    net: Net
    u_mean: Tensor
    u_scale: Tensor

    def __call__(self, x: Tensor, product: Product | None = None) -> Tensor:
        """Action mean ``mu_theta(x)``: ``[..., dX] -> [..., dU]``."""
        z = (x - self.x_mean) / self.x_std
        return torch.addcmul(self.u_mean, self.net(z, product), self.u_scale)


class GaussianPolicy(torch.nn.Module):
    """``pi_theta(u | x) = N(mu_theta(x), diag(sigma^2))`` with
    ``mu_theta(x) = u_mean + u_scale * MLP((x - x_mean) / x_std)``.

    The input whitening (``x_mean``, ``x_std``, the latter floored at ``std_floor``), the action
    variance ``sigma^2`` and the output scaling (``u_mean``, ``u_scale``) are set by the S-step:
    the whitening from the training states, ``sigma^2`` in closed form, and the output scaling
    from the teachers' means and ``sigma`` itself, so the MLP's outputs are in units of the
    policy's own standard deviation on every joint of any arm (see
    :func:`lolgps_torch.policy.sstep.distill`); the MLP weights by Adam. ``trained`` (a buffer, so it survives save/load) says whether an S-step has run.

    :param dX: state size. :param dU: action size.
    :param config: architecture and training settings (defaults: :class:`PolicyConfig`).
    :param device: where parameters and buffers live.
    """

    x_mean: Tensor
    x_std: Tensor
    u_mean: Tensor
    u_scale: Tensor
    variance: Tensor
    trained_flag: Tensor
    guard_torque: Tensor
    guard_speed: Tensor
    guard_brake: Tensor
    guard_retreat: Tensor
    guard_hover: Tensor

    def __init__(
        self,
        dX: int,
        dU: int,
        config: PolicyConfig | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__()
        self.config = config if config is not None else PolicyConfig()
        self.dX, self.dU = dX, dU
        generator = torch.Generator().manual_seed(self.config.seed)
        self.net: torch.nn.Sequential = _mlp(dX, dU, self.config.hidden_sizes, generator)
        self.gain = torch.nn.Linear(self.config.hidden_sizes[-1], dU * dX, dtype=torch.float64)
        torch.nn.init.zeros_(self.gain.weight)
        torch.nn.init.zeros_(self.gain.bias)
        self.gain.requires_grad_(self.config.feedback)
        self.register_buffer("x_mean", torch.zeros(dX, dtype=torch.float64))
        self.register_buffer("x_std", torch.ones(dX, dtype=torch.float64))
        self.register_buffer("u_mean", torch.zeros(dU, dtype=torch.float64))
        self.register_buffer("u_scale", torch.ones(dU, dtype=torch.float64))
        self.register_buffer("variance", torch.ones(dU, dtype=torch.float64))  # diag(Sigma_pi)
        self.register_buffer("trained_flag", torch.zeros((), dtype=torch.bool))
        off = Guard.off(dU)
        self.register_buffer("guard_torque", off.torque)
        self.register_buffer("guard_speed", off.speed)
        self.register_buffer("guard_brake", off.brake)
        self.register_buffer("guard_retreat", off.retreat)
        self.register_buffer("guard_hover", off.hover)
        self.to(device)

    def forward(self, x: Tensor, product: Product | None = None) -> Tensor:
        """Action mean ``mu_theta(x)``: ``[..., dX] -> [..., dU]``; ``product(x, W)`` in place
        of each matrix product ``x W^T`` (None: torch's; a row-wise one for rows stepped
        together, :func:`lolgps_torch.sim.rollout.matmul_rows`)."""
        return self.acting()(x, product)

    def unscaled(self, z: Tensor, product: Product | None = None) -> Tensor:
        """The net's output at whitened states ``z``, before the output scaling."""
        return self.layers()(z, product)

    def layers(self) -> Net:
        """The net's weights as plain tensors (:class:`Net`), valid while no weight tensor is
        replaced (in-place updates are seen)."""
        layers = tuple(
            Layer(m.weight, m.bias) if isinstance(m, torch.nn.Linear) else m for m in self.net
        )
        gain = Layer(self.gain.weight, self.gain.bias) if self.config.feedback else None
        return Net(layers, gain)

    def acting(self) -> Acting:
        """``mu_theta`` as plain tensors (:class:`Acting`), valid while no weight or buffer
        tensor is replaced."""
        return Acting(self.x_mean, self.x_std, self.layers(), self.u_mean, self.u_scale)

    @property
    def guard(self) -> Guard:
        """The bounds the acting policy keeps to (off until an S-step sets them)."""
        return Guard(
            self.guard_torque, self.guard_speed, self.guard_brake, self.guard_retreat,
            self.guard_hover,
        )  # fmt: skip

    @torch.no_grad()
    def set_guard(self, guard: Guard) -> None:
        """Set the acting policy's bounds (the trip speeds' steps may differ from before)."""
        self.guard_torque.copy_(guard.torque)
        self.guard_speed = guard.speed.to(self.guard_speed).clone()
        self.guard_brake.copy_(guard.brake)
        self.guard_retreat.copy_(guard.retreat)
        self.guard_hover.copy_(guard.hover)

    def covariance(self) -> Tensor:
        """``Sigma_pi = diag(sigma^2)``, ``[dU, dU]``."""
        return torch.diag(self.variance)

    @property
    def trained(self) -> bool:
        """Whether an S-step has fitted this policy (before that there is no ``p_pre``)."""
        return bool(self.trained_flag)

    @trained.setter
    def trained(self, value: bool) -> None:
        self.trained_flag.fill_(value)

    @torch.no_grad()
    def set_whitening(self, x: Tensor) -> None:
        """Whitening from states ``x: [M, dX]``: mean and std (biased, floored at ``std_floor``)."""
        if x.ndim != 2 or x.shape[1] != self.dX or x.shape[0] < 1:
            raise LolgpsError(f"whitening needs states [M >= 1, {self.dX}], got {tuple(x.shape)}")
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0, correction=0).clamp_min(self.config.std_floor))

    @torch.no_grad()
    def set_output_scaling(self, mean: Tensor, scale: Tensor) -> None:
        """Set ``u_mean: [dU]`` and ``u_scale: [dU]`` (finite, scale positive)."""
        good = mean.isfinite().all() & scale.isfinite().all() & (scale > 0).all()
        if mean.shape != (self.dU,) or scale.shape != (self.dU,) or not bool(good):
            raise LolgpsError(f"policy output scaling must be finite [{self.dU}], scale positive")
        self.u_mean.copy_(mean)
        self.u_scale.copy_(scale)

    @torch.no_grad()
    def set_variance(self, variance: Tensor) -> None:
        """Set the diagonal ``sigma^2: [dU]`` of ``Sigma_pi`` (positive)."""
        if variance.shape != (self.dU,) or not bool(((variance > 0) & variance.isfinite()).all()):
            raise LolgpsError(
                f"policy variance must be finite and positive [{self.dU}], got {variance}"
            )
        self.variance.copy_(variance)

    def description(self) -> dict[str, Any]:
        """What rebuilds this policy's architecture, as JSON-able data: ``dX``, ``dU`` and the
        :class:`PolicyConfig` (its weights are :meth:`state_dict`)."""
        return {"dX": self.dX, "dU": self.dU, "config": asdict(self.config)}

    @classmethod
    def from_state(
        cls,
        description: dict[str, Any],
        state: dict[str, Tensor],
        device: torch.device | str = "cpu",
    ) -> GaussianPolicy:
        """The policy of :meth:`description` with the weights and buffers ``state``; a
        malformed description or a state of other shapes is a :class:`LolgpsError`."""
        try:
            settings = dict(description["config"])
            settings["hidden_sizes"] = tuple(settings["hidden_sizes"])
            policy = cls(int(description["dX"]), int(description["dU"]), PolicyConfig(**settings))
            # checkpoints from before the output scaling: scale 1, offset 0 is the same policy
            state = {"u_mean": policy.u_mean, "u_scale": policy.u_scale, **state}
            state = {"gain.weight": policy.gain.weight, "gain.bias": policy.gain.bias, **state}
            # checkpoints from before the guard: unguarded
            state = {**{k: v for k, v in policy.state_dict().items() if k.startswith("guard_")},
                     **state}  # fmt: skip
            # checkpoints from before the model's brake: a fitted gain matrix, now the share
            if state["guard_brake"].ndim == 2:
                braked = bool(state["guard_brake"].any())
                state["guard_brake"] = policy.guard_brake.new_tensor(
                    policy.config.guard_brake if braked else 0.0
                )
            # checkpoints from before the per-step trip speeds: one row for every step
            speed = state["guard_speed"]
            policy.guard_speed = torch.empty_like(speed if speed.ndim == 2 else speed[None])
            state["guard_speed"] = speed.reshape(policy.guard_speed.shape)
            policy.load_state_dict(state)
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            text = str(error).strip()
            raise LolgpsError(text.splitlines()[0] if text else repr(error)) from None
        return policy.to(device)
