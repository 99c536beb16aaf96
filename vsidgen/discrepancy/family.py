"""Refits of candidates that add states, one compilation per shape and worker.

Candidates that add states cannot be gated terms of one model (:mod:`.gated`: an inert added
state still changes the assumed density), so each used to compile its own programs for its
refit: stage 0 (smoothing with the candidate at its nesting point), stages 1 and 2, the
validation smoothing. Candidates of one *shape* — the same numbers of added states, of new
parameters and of new free parameters, e.g. the first-order modes ``missing_dynamics`` of
several equations, or a lag and a Padé delay of one input — give models with the same numbers
of states, inputs, outputs and parameters; their refits can run as fits of one
:class:`~vsidgen.estimator.ModelFamily`, whose objective switches between the members at run
time (``jax.lax.switch``), so the members' programs are traced once each and compiled once for
all of them. Each refit is the member's own problem (its statistics equal the per-candidate
refit's up to the optimiser's tolerance; ``tests/test_family.py``).

A family is refitted in one engine task (the compiled programs live in that worker process).
The members of a shape are split into at most as many families as the engine has workers
(:func:`family_chunks`), so that the refits still spread over every worker; a chunk of one
candidate is an ordinary refit task. Results, failures and the time limit stay per
candidate (the family task, ``search._family_task``, returns one outcome per member;
:func:`member_outcomes` unpacks them).
"""

from __future__ import annotations

import dataclasses
import os
import time

from ..engine import TaskOutcome, TaskStatus
from .base import Candidate

#: prefix of the engine key of a family task (followed by its members' keys)
FAMILY_KEY = "family:"


@dataclasses.dataclass(frozen=True)
class TaskDeadline:
    """The engine's deadline (``time.monotonic()`` of the process that set it) carried into a
    task: checked on the monotonic clock in that process (serial engine; tests may move that
    clock) and as wall-clock time (``time.time()``) in any other process, e.g. a worker on
    another machine."""

    pid: int
    monotonic: float
    wall: float

    @classmethod
    def of(cls, deadline: float | None) -> "TaskDeadline | None":
        if deadline is None:
            return None
        return cls(os.getpid(), float(deadline), time.time() + (deadline - time.monotonic()))

    def left(self) -> float:
        """Seconds to the deadline (negative once it has passed)."""
        if os.getpid() == self.pid:
            return self.monotonic - time.monotonic()
        return self.wall - time.time()

    def passed(self) -> bool:
        return self.left() <= 0.0


def family_shape(c: Candidate) -> tuple[int, int, int] | None:
    """(added states, new parameters, new free parameters) of a candidate that adds states
    (None when it adds none: such candidates are gated instead)."""
    if not c.states:
        return None
    return len(c.states), len(c.parameters), sum(1 for p in c.parameters if not p.fixed)


def family_chunks(cands, workers: int) -> list[list[Candidate]]:
    """The candidates that add states, grouped by :func:`family_shape` (first seen, in order)
    and each group split round-robin into at most ``workers`` chunks; chunks of one
    candidate included (they are refitted alone). Candidates without states are left out."""
    shapes: dict = {}
    for c in cands:
        s = family_shape(c)
        if s is not None:
            shapes.setdefault(s, []).append(c)
    out = []
    for members in shapes.values():
        n = max(1, min(int(workers), len(members)))
        out += [members[j::n] for j in range(n)]
    return out


def family_key(members) -> str:
    return FAMILY_KEY + "+".join(c.key for c in members)


def member_outcomes(oc: TaskOutcome, keys) -> list[TaskOutcome]:
    """The per-candidate outcomes of a finished engine task: a family task's members
    (``keys``) from its value, or all of them with the task's status when the task itself
    failed, was lost or was cancelled; any other task as it is."""
    if not oc.key.startswith(FAMILY_KEY):
        return [oc]
    if oc.status is TaskStatus.DONE:
        return list(oc.value)
    return [TaskOutcome(k, oc.status, error=oc.error, wall_s=oc.wall_s) for k in keys]


__all__ = ["FAMILY_KEY", "TaskDeadline", "family_chunks", "family_key", "family_shape", "member_outcomes"]
