"""Where the residual may act: the phase gate."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["PhaseGate", "as_batch", "gate_from_config"]


def as_batch(observation: Any) -> tuple[NDArray[Any], bool]:
    """``(observation as (n, obs_dim), whether it was a single (obs_dim,) observation)``."""
    obs = np.asarray(observation)
    if obs.ndim == 1:
        return obs[None, :], True
    if obs.ndim != 2:
        raise ValueError(
            f"observation must have shape (obs_dim,) or (n_envs, obs_dim), got {obs.shape}"
        )
    return obs, False


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value}")
    return value


@dataclass(frozen=True)
class PhaseGate:
    """Open the residual in a window of the phase (normalised time, 0 at reset, 1 at the end of
    the demonstrated motion).

    ``gate = 0`` for ``phase < start - ramp``, rises linearly to 1 at ``start``, stays 1 up to
    ``end`` (default: forever, so the residual can finish a press the base stopped short of) and
    is 0 after ``end``.

    Arguments:
        start: phase at which the gate is fully open, in ``[0, 1]``.
        end: phase after which it closes again (``inf``: never); ``end > start``.
        ramp: width of the linear ramp before ``start`` (0: a step), in ``[0, 1]``.
        source: where the phase comes from. ``"policy"``: ``base.phase(observation)`` (the GP
            policy's own normalised time). ``"observation"``: ``observation[..., time_index] /
            time_scale`` (e.g. the env's ``time`` entry in seconds divided by the demonstrated
            duration); use it for bases without a ``phase`` method.
        time_index: index of the time entry in the observation (``source="observation"``).
        time_scale: divisor that turns that entry into a phase (finite, positive).

    Why the phase and not the env's stage flags: ``cup_placed`` is the simulator's judgement
    (tolerance to the spout axis), which a deployed robot does not have; the phase is what the
    time-indexed GP policy runs on anyway. Why not the GP's predicted variance alone: the machine
    frame is tight twice (placing and pressing), so a variance gate needs the phase to tell the
    two apart.
    """

    start: float = 0.75
    end: float = math.inf
    ramp: float = 0.05
    source: str = "policy"
    time_index: int | None = None
    time_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.source not in ("policy", "observation"):
            raise ValueError(f"source must be 'policy' or 'observation', got {self.source!r}")
        if self.source == "observation" and (
            not isinstance(self.time_index, int)
            or isinstance(self.time_index, bool)
            or self.time_index < 0
        ):
            raise ValueError(
                f"source='observation' needs time_index (the time entry's index, an int >= 0), "
                f"got {self.time_index!r}"
            )
        start = _finite("start", self.start)
        ramp = _finite("ramp", self.ramp)
        scale = _finite("time_scale", self.time_scale)
        if not 0.0 <= start <= 1.0:
            raise ValueError(f"start must be a phase in [0, 1], got {start}")
        if not 0.0 <= ramp <= 1.0:
            raise ValueError(f"ramp must be in [0, 1], got {ramp}")
        if not (self.end > start):  # also false for NaN
            raise ValueError(f"end must be > start ({start}), got {self.end}")
        if scale <= 0:
            raise ValueError(f"time_scale must be positive, got {scale}")

    def phase(self, observation: NDArray[Any], base: Any = None) -> NDArray[np.float64]:
        """Phase per row of a batch ``observation (n, obs_dim)`` -> ``(n,)``."""
        obs, _ = as_batch(observation)
        if self.source == "observation":
            return obs[:, self.time_index].astype(np.float64) / self.time_scale
        phase_fn = getattr(base, "phase", None)
        if not callable(phase_fn):
            raise TypeError(
                f"PhaseGate(source='policy') needs a base policy with a phase(observation) "
                f"method; {type(base).__name__} has none. Use PhaseGate(source='observation', "
                f"time_index=..., time_scale=...) instead."
            )
        phase = np.asarray(phase_fn(obs), dtype=np.float64).reshape(-1)
        if phase.shape != (obs.shape[0],):
            raise ValueError(f"base.phase returned shape {phase.shape}, expected ({obs.shape[0]},)")
        return phase

    def __call__(self, observation: NDArray[Any], base: Any = None) -> NDArray[np.float32]:
        """Gate value in ``[0, 1]`` per row of ``observation (n, obs_dim)`` -> ``(n,)``."""
        phase = self.phase(observation, base)
        if self.ramp > 0:
            rise = np.clip((phase - (self.start - self.ramp)) / self.ramp, 0.0, 1.0)
        else:
            rise = (phase >= self.start).astype(np.float64)
        gate = np.where(phase > self.end, 0.0, rise)
        return gate.astype(np.float32)

    def to_config(self) -> dict[str, Any]:
        """A JSON-able dict that :func:`gate_from_config` turns back into this gate."""
        cfg = dataclasses.asdict(self)
        cfg["end"] = None if math.isinf(self.end) else self.end
        return {"type": "phase", **cfg}


_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "start": (int, float),
    "end": (int, float, type(None)),
    "ramp": (int, float),
    "source": (str,),
    "time_index": (int, type(None)),
    "time_scale": (int, float),
}


def gate_from_config(config: Mapping[str, Any]) -> PhaseGate:
    """Rebuild a gate from :meth:`PhaseGate.to_config`'s dict (e.g. read from a policy file);
    every field is type- and range-checked."""
    if not isinstance(config, Mapping):
        raise ValueError(f"gate settings must be an object, got {type(config).__name__}")
    cfg = dict(config)
    kind = cfg.pop("type", None)
    if kind != "phase":
        raise ValueError(f"unknown gate type {kind!r} (known: 'phase')")
    unknown = set(cfg) - set(_FIELD_TYPES)
    if unknown:
        raise ValueError(f"unknown PhaseGate settings {sorted(unknown)}")
    for key, value in cfg.items():
        if not isinstance(value, _FIELD_TYPES[key]) or isinstance(value, bool):
            raise ValueError(f"gate setting {key!r} has the wrong type ({type(value).__name__})")
    if cfg.get("end") is None:
        cfg["end"] = math.inf
    return PhaseGate(**cfg)
