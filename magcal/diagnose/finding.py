"""Finding: one effect that earned its place, as a value (the JSON shape of a finding)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping


@dataclass(frozen=True)
class Finding:
    effect: str
    summary: str
    where: Mapping[str, Any] = field(default_factory=dict)
    evidence: Mapping[str, Any] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "effect": self.effect,
            "summary": self.summary,
            "where": dict(self.where),
            "evidence": dict(self.evidence),
            "params": dict(self.params),
        }
