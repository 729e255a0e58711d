"""`envs.frames.FrameGate`: a simulator's render call, drawn only when asked, on a stand-in simulator."""

import numpy as np
import pytest

from lerobot_policy_ebvla.envs.frames import FrameGate, check_render_every


class CountingSimulator:
    """Each render draws a new frame: its pixels are the number of frames drawn so far."""

    def __init__(self):
        self.drawn = 0

    def render(self, camera="front"):
        self.drawn += 1
        return np.full((2, 2), self.drawn)


def test_a_skipped_step_repeats_each_cameras_last_frame_without_drawing():
    simulator, gate = CountingSimulator(), FrameGate()
    gate.attach(simulator)
    gate.attach(simulator)  # gating the same simulator again changes nothing
    front, side = simulator.render(), simulator.render(camera="side")
    gate.skip = True
    assert simulator.render()[0, 0] == front[0, 0] and simulator.render(camera="side")[0, 0] == side[0, 0]
    assert simulator.drawn == 2
    gate.skip = False
    assert simulator.render()[0, 0] == 3


def test_an_uncached_frame_is_drawn_fresh_and_leaves_the_repeated_one():
    simulator, gate = CountingSimulator(), FrameGate()
    gate.attach(simulator)
    observed = simulator.render()
    gate.skip = True
    with gate.uncached():
        assert simulator.render()[0, 0] == 2  # a video's frame: the scene now
    assert simulator.render()[0, 0] == observed[0, 0]


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "8"])
def test_render_every_must_be_a_positive_int(value):
    with pytest.raises(ValueError, match="`render_every` must be an int >= 1"):
        check_render_every(value)
