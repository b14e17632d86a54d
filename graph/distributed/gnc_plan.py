"""GNC on a fixed schedule of rounds, every decision a robot's own at its step: what lets robot processes, which
share no clock and hear no team-wide "done", run the same GNC as simulated robots.

The simulated team's GNC (graph.distributed.team.solve_distributed without a plan) is driven from outside: the
team solves until still, agrees on GNC's initial mu in separate exchanges, updates every robot's weights between
rounds and stops when every weight is 0 or 1. A plan fixes all of that in advance, by round number (a robot's step
counter):

  rounds 1 .. ls                   least squares, every weight 1
  round ls + 1                     each robot proposes GNC's initial mu from its owned loops, at its step
  rounds ls + 1 .. ls + relay      the proposals travel with the estimates (the smallest heard, relayed: `relay` at
                                   least the team's diameter; the team's size always is)
  round g0 = ls + relay + 1 + j*r  GNC step j < steps: the robot sets its owned loops' weights for mu = mu0 *
                                   mu_step^j at its step (mu0: the smallest proposal it holds), then r rounds
  the last `final` rounds          least squares with the final weights

A robot decides at its own step from what it holds then: its neighbours of lower colour have stepped in this
round, the others in the last, in processes as in the simulated team, so both follow the same arithmetic. Steps
go on after the weights are binary (nobody knows that the whole team's are): they change nothing but cost rounds.
"""

from __future__ import annotations

from dataclasses import dataclass

from swarmsplat.kernels.errors import InputError


@dataclass
class GncPlan:
    ls_rounds: int = 10
    relay_rounds: int = 8
    steps: int = 25
    step_rounds: int = 4
    final_rounds: int = 30
    mu_step: float = 1.4
    barc: float = 0.0  # GNC's inlier threshold (half the chi-square quantile of the residual's dimension)

    def __post_init__(self):
        if min(self.ls_rounds, self.relay_rounds, self.steps, self.step_rounds) < 1 or self.final_rounds < 0:
            raise InputError("a GNC plan needs at least one round of each phase")
        if not (self.mu_step > 1 and self.barc > 0):
            raise InputError("a GNC plan needs mu_step > 1 and barc > 0")

    @property
    def total(self) -> int:
        return self.ls_rounds + self.relay_rounds + self.steps * self.step_rounds + self.final_rounds

    def proposes(self, k: int) -> bool:
        """Round k is when each robot proposes GNC's initial mu."""
        return k == self.ls_rounds + 1

    def relays(self, k: int) -> bool:
        """Round k's estimates carry the proposals."""
        return self.ls_rounds < k <= self.ls_rounds + self.relay_rounds

    def gnc_step(self, k: int) -> int | None:
        """The GNC step that starts at round k, or None."""
        g = k - (self.ls_rounds + self.relay_rounds + 1)
        if g < 0 or g % self.step_rounds or g // self.step_rounds >= self.steps:
            return None
        return g // self.step_rounds
