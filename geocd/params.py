"""What every frozen parameter dataclass of geocd shares: copies with changes, and a JSON form.

``StereoParams``, ``ProbChangeParams`` and ``SynthParams`` inherit :class:`ParamsMixin`; tuples travel as JSON
lists and come back as tuples, and unknown keys are a :class:`~geocd.errors.ConfigError` naming the known ones.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from .errors import ConfigError


class ParamsMixin:
    """Mix into a frozen dataclass; ``_kind`` names the parameter set in error messages."""

    _kind = "geocd"

    def replace(self, **changes: Any):
        """A copy with ``changes`` (validated again by the dataclass)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain dict, tuples as lists (JSON-ready)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict):
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`ConfigError`."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"unknown {cls._kind} parameters {sorted(unknown)}; known: {sorted(known)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})
