"""Drawing only the frames a chunked policy reads (`--env.render_every`), for both simulators.

A policy that acts in chunks of N steps (`n_action_steps`) reads the reset's frame and every N-th step's; the env
draws the others for nobody. On two CPU cores, with MuJoCo rendering in software, drawing is most of a rollout's
time (LIBERO: 62 % of a step; MetaWorld: about 30 ms of a 32 ms step at 64 px). With `render_every=N` the env
draws the frames that are read, each exactly as with N = 1, and the steps between repeat the last ones.
"""

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np


def check_render_every(render_every: int) -> None:
    """Raises a ValueError naming `render_every` unless it is an int >= 1."""
    if isinstance(render_every, bool) or not isinstance(render_every, int) or render_every < 1:
        raise ValueError(
            f"`render_every` must be an int >= 1 (the policy's n_action_steps, or 1), got {render_every!r}."
        )


class FrameGate:
    """Stands in for a simulator's `render`: while `skip` is set, a camera that rendered before returns its last
    frame instead of drawing a new one. `restart()` at a reset and `advance()` at each policy step set `skip` for
    the frames of step t with t % `every` != 0.

    Gating the render call itself (rather than rendering after the step) keeps the frames that are drawn identical
    to those of an ungated env: robosuite, for one, draws its cameras at a step's first physics substep.
    """

    def __init__(self, every: int = 1):
        check_render_every(every)
        self.every = every
        self.skip = False
        self._steps = 0
        self._last: dict[Any, np.ndarray] = {}
        self._gated: Any = None
        self._uncached = False

    def attach(self, simulator: Any) -> None:
        """Gates `simulator.render`; a simulator built anew (LIBERO's hard reset) is gated again."""
        if simulator is self._gated:
            return
        render = simulator.render

        def gated_render(*args: Any, **kwargs: Any) -> np.ndarray:
            if self._uncached:
                return render(*args, **kwargs)
            key = (args, tuple(sorted(kwargs.items())))
            if self.skip and key in self._last:
                return self._last[key]
            frame = render(*args, **kwargs)
            self._last[key] = frame
            return frame

        simulator.render = gated_render
        self._gated = simulator

    def restart(self) -> None:
        """A reset: its frame is drawn, and policy steps count from it."""
        self._steps, self.skip = 0, False

    def advance(self) -> None:
        """A policy step: its frame is drawn on every `every`-th step only."""
        self._steps += 1
        self.skip = self._steps % self.every != 0

    @contextmanager
    def uncached(self) -> Iterator[None]:
        """Draws fresh frames that the policy's observations never see (a video's), leaving the gate's own."""
        self._uncached = True
        try:
            yield
        finally:
            self._uncached = False
