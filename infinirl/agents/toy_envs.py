"""Toy agent environments for tests and smoke runs on random models: they hand a turn to the
environment at stop strings a random model emits often, so multi-turn plumbing (masks, budgets,
metrics, resume) runs without a model that knows any tool."""

from __future__ import annotations

from collections.abc import Sequence

from infinirl.agents.loop import AgentEnv, AgentStep

__all__ = ["EchoEnv"]


class EchoEnv(AgentEnv):
    """Ends a turn at any of ``stops`` and answers ``observation`` until it has answered
    ``answers`` times; the turn after that ends the trajectory."""

    def __init__(self, stops: Sequence[str] = ("e",), observation: str = " [ok] ", answers: int = 2):
        if not stops or any(not s for s in stops):
            raise ValueError("stops: give at least one non-empty stop string")
        self.stop_strings = tuple(stops)
        self.observation, self.answers, self.answered = observation, answers, 0
        self.problem = None

    def reset(self, problem) -> None:
        self.problem = problem

    def step(self, turn: str) -> AgentStep:
        if self.answered >= self.answers:
            return AgentStep(done=True)
        self.answered += 1
        knows = int(self.problem is not None)
        return AgentStep(observation=self.observation, info={"echoes": 1, "knows_problem": knows})
