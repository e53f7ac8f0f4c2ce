"""Parameter registry entries: what a model parameter is, its unit, its null value and its range.

Every physics term and material lists its parameters as ``parameters = {name: ParameterInfo}``
(DESIGN §1.4). ``null`` is the value at which the term vanishes and the model is exactly the
model without it (``None`` for parameters of the base model, which have no null). ``low`` and
``high`` bound the admissible values; ``low_inclusive`` / ``high_inclusive`` say whether the
bounds themselves are admissible.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch


class ParameterError(ValueError):
    """A parameter value is missing or outside its admissible range."""


@dataclass(frozen=True)
class ParameterInfo:
    """One parameter: ``name``, ``unit`` (mm, MPa, N system), ``null`` value (None: a base-model
    parameter), admissible range ``low .. high`` and a one-line ``description``."""

    name: str
    unit: str
    null: float | None
    low: float = -math.inf
    high: float = math.inf
    description: str = ""
    low_inclusive: bool = True
    high_inclusive: bool = True

    def renamed(self, name: str) -> "ParameterInfo":
        return replace(self, name=name)

    def admissible(self, values: torch.Tensor) -> torch.Tensor:
        """Elementwise: finite and within the range (bool tensor of the shape of ``values``)."""
        lo = values >= self.low if self.low_inclusive else values > self.low
        hi = values <= self.high if self.high_inclusive else values < self.high
        return torch.isfinite(values) & lo & hi

    def range_text(self) -> str:
        left = "[" if self.low_inclusive else "("
        right = "]" if self.high_inclusive else ")"
        return f"{left}{self.low:g}, {self.high:g}{right} {self.unit}"


def check_parameters(infos: dict[str, ParameterInfo], params: dict[str, torch.Tensor], owner: str) -> None:
    """Raise ParameterError naming the owner, parameter and member whose value is missing, not
    finite or outside its admissible range."""
    for key, info in infos.items():
        if key not in params:
            raise ParameterError(f"{owner} needs parameter '{key}' ({info.unit}); got {sorted(params)}")
        v = torch.as_tensor(params[key])
        bad = ~info.admissible(v)
        if bad.any():
            m = int(torch.nonzero(bad.reshape(-1))[0, 0])
            raise ParameterError(
                f"parameter {key} of member {m} is {float(v.reshape(-1)[m])!r}; {owner} needs {key} in "
                f"{info.range_text()}" + (f" ({info.description})" if info.description else "")
            )
