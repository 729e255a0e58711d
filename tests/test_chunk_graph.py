"""`compile_mode="chunk-graph"`: a chunk's whole refinement, drawn-ahead noise and all, is the eager chunk.

The CUDA capture itself needs a GPU (timed in research/docs/vlm_gpu.md); here the bookkeeping around it runs with a
stand-in recorder whose replay re-runs the recorded chain on its buffers, as a replayed graph recomputes its
recorded kernels on whatever its input buffers hold.
"""

import logging

import pytest
import torch

from lerobot_policy_ebvla import compile_ebvla
from lerobot_policy_ebvla.compile_ebvla import RefinementGraphs
from lerobot_policy_ebvla.mcmc import RTCPrefix, draw_langevin_noise, refine_actions

from .conftest import tiny_batch
from .test_compile_mode import BATCH_SIZE, aot_eager_compiles, chunk, clear_compiled, make_policy

STEPS = [0.05] * 6
SETTINGS = {"temperature": 2.0, "langevin_std": 0.01, "grad_clip": 1.0, "action_clamp": 1.0}


def quadratic_energy(target: torch.Tensor):
    return lambda a: ((a - target) ** 2).sum(dim=-1)


def test_noise_drawn_ahead_is_the_noise_the_steps_draw():
    """The same generator state gives the same chain, whether the steps draw their noise or get it."""
    target = torch.rand(3, 4, 2)
    initial = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(1))
    drawing = refine_actions(
        quadratic_energy(target), initial, STEPS, generator=torch.Generator().manual_seed(5), **SETTINGS
    )
    noise = draw_langevin_noise(len(STEPS), initial, torch.Generator().manual_seed(5))
    given = refine_actions(quadratic_energy(target), initial, STEPS, noise=noise, **SETTINGS)
    assert noise.shape == (len(STEPS), 3, 4, 2)
    assert torch.equal(given.actions, drawing.actions)
    assert torch.equal(given.step_energies, drawing.step_energies)


def test_noise_of_the_wrong_shape_is_rejected_naming_it():
    initial = torch.zeros(2, 4, 2)
    with pytest.raises(ValueError, match=r"`noise` must hold one draw per step, shaped \(6, 2, 4, 2\)"):
        refine_actions(quadratic_energy(initial), initial, STEPS, noise=torch.zeros(5, 2, 4, 2), **SETTINGS)


def test_without_cuda_a_chunk_graph_policy_gives_the_eager_chunk(monkeypatch, caplog):
    """Off CUDA the context compiles as "default" (here `aot_eager`) and the chain runs eagerly, with a warning."""
    modes = aot_eager_compiles(monkeypatch)
    clear_compiled()
    eager = make_policy()
    batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=17, with_action=False)
    try:
        with caplog.at_level(logging.WARNING, logger=compile_ebvla.__name__):
            got = chunk(make_policy(compile_mode="chunk-graph"), batch)
    finally:
        clear_compiled()
    assert modes == [None]  # the context encoder alone is compiled; the chain is the eager head's
    assert "`compile_mode='chunk-graph'` replays CUDA graphs" in caplog.text
    for got_tensor, expected in zip(got, chunk(eager, batch), strict=True):
        torch.testing.assert_close(got_tensor, expected, atol=1e-6, rtol=1e-6)


class StandInRecorder:
    """Records like `record_cuda_graph`: the chain runs once on the buffers, and each replay runs it again there,
    writing into the first outputs in place."""

    def __init__(self):
        self.captures = 0

    def __call__(self, fn, warmup_calls):
        self.captures += 1
        outputs = fn()

        def replay():
            (result, final), (new_result, new_final) = outputs, fn()
            for old, new in (
                (result.actions, new_result.actions),
                (result.step_energies, new_result.step_energies),
                (result.diverged, new_result.diverged),
                (final, new_final),
            ):
                old.copy_(new)

        return replay, outputs


@pytest.fixture
def recorded(monkeypatch) -> StandInRecorder:
    """Chains on this CPU go through the graph bookkeeping, with the stand-in recorder."""
    recorder = StandInRecorder()
    monkeypatch.setattr(compile_ebvla, "record_cuda_graph", recorder)
    monkeypatch.setattr(RefinementGraphs, "records", staticmethod(lambda initial: True))
    return recorder


def energy_chain(weight: torch.Tensor):
    """A refinement chain of `weight`-scaled quadratic energies around kv's first key, as the model's chain is
    built: (kv, a^(0), noise, prefix) -> (result, final energies)."""

    def chain(kv, initial, noise, prefix):
        target = kv[0][0]
        energy = lambda a: weight * ((a - target) ** 2).sum(dim=-1)  # noqa: E731
        result = refine_actions(energy, initial, STEPS, noise=noise, prefix=prefix, **SETTINGS)
        return result, energy(result.actions).mean(dim=-1)

    return chain


def inputs(seed: int, batch_size: int = 2):
    generator = torch.Generator().manual_seed(seed)
    target = torch.rand(batch_size, 4, 2, generator=generator)
    initial = torch.randn(batch_size, 4, 2, generator=generator)
    noise = draw_langevin_noise(len(STEPS), initial, generator)
    return [(target, target)], initial, noise


def test_replays_read_each_call_s_inputs_and_return_copies(recorded):
    weight = torch.ones(())
    chain, graphs = energy_chain(weight), RefinementGraphs()
    first_inputs, second_inputs = inputs(1), inputs(2)
    first = graphs(chain, [weight], *first_inputs, None)
    second = graphs(chain, [weight], *second_inputs, None)
    assert recorded.captures == 1  # one shape, one graph
    for got, call_inputs in ((first, first_inputs), (second, second_inputs)):
        expected = chain(*call_inputs, None)
        assert torch.equal(got[0].actions, expected[0].actions)
        assert torch.equal(got[0].step_energies, expected[0].step_energies)
        assert torch.equal(got[1], expected[1])


def test_a_graph_per_shape_and_prefix_the_oldest_dropped(recorded):
    weight = torch.ones(())
    chain, graphs = energy_chain(weight), RefinementGraphs(max_graphs=2)
    kv, initial, noise = inputs(1)
    prefix = RTCPrefix(torch.zeros_like(initial), held_steps=1, weights=torch.ones(4), guidance_weight=1.0)
    graphs(chain, [weight], kv, initial, noise, None)
    got = graphs(chain, [weight], kv, initial, noise, prefix)
    assert recorded.captures == 2
    assert torch.equal(got[0].actions, chain(kv, initial, noise, prefix)[0].actions)
    assert torch.equal(got[0].actions[:, 0], torch.zeros(2, 2))  # the held action
    graphs(chain, [weight], *inputs(3, batch_size=3), None)
    assert len(graphs.graphs) == 2 and recorded.captures == 3
    graphs(chain, [weight], kv, initial, noise, None)  # dropped as the least recently used: captured again
    assert recorded.captures == 4


def test_weights_in_new_memory_drop_the_graphs_and_updates_in_place_are_read(recorded):
    weight = torch.ones(())
    graphs, call_inputs = RefinementGraphs(), inputs(1)
    graphs(energy_chain(weight), [weight], *call_inputs, None)
    weight.mul_(3.0)  # an optimizer's step: same memory, the recorded graph reads the new value
    in_place = graphs(energy_chain(weight), [weight], *call_inputs, None)
    assert recorded.captures == 1
    assert torch.equal(in_place[1], energy_chain(weight)(*call_inputs, None)[1])
    moved = weight.clone()  # `policy.to(...)`: new memory, the old graphs would read freed buffers
    graphs(energy_chain(moved), [moved], *call_inputs, None)
    assert recorded.captures == 2 and len(graphs.graphs) == 1


def test_a_chunk_graph_policy_through_the_recorder_gives_the_eager_chunk(recorded, monkeypatch):
    """The policy's own chain (eager head, drawn-ahead noise, final energy) through the graph bookkeeping,
    two chunks in a row: each is the eager policy's chunk for its observation."""
    aot_eager_compiles(monkeypatch)
    clear_compiled()
    eager = make_policy()
    policy = make_policy(compile_mode="chunk-graph")
    try:
        for seed in (19, 23):
            batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=seed, with_action=False)
            for got_tensor, expected in zip(chunk(policy, batch), chunk(eager, batch), strict=True):
                torch.testing.assert_close(got_tensor, expected, atol=1e-6, rtol=1e-6)
    finally:
        clear_compiled()
    assert recorded.captures == 1


def test_with_early_stop_the_steps_are_graphed_one_by_one(monkeypatch):
    """A stop decided on the host cannot be recorded: the energy of each step is compiled instead."""
    modes = aot_eager_compiles(monkeypatch)
    clear_compiled()
    eager = make_policy(early_stop_tol=1e-3)
    batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=29, with_action=False)
    try:
        got = chunk(make_policy(compile_mode="chunk-graph", early_stop_tol=1e-3), batch)
    finally:
        clear_compiled()
    assert modes == [None, None]  # the context and the step's energy, as "default" off CUDA
    for got_tensor, expected in zip(got, chunk(eager, batch), strict=True):
        torch.testing.assert_close(got_tensor, expected, atol=1e-5, rtol=1e-5)


def test_a_failed_capture_refines_eagerly_and_says_why(monkeypatch, caplog):
    def failing_recorder(fn, warmup_calls):
        raise RuntimeError("operation not permitted when stream is capturing")

    monkeypatch.setattr(compile_ebvla, "record_cuda_graph", failing_recorder)
    monkeypatch.setattr(RefinementGraphs, "records", staticmethod(lambda initial: True))
    weight, graphs, call_inputs = torch.ones(()), RefinementGraphs(), inputs(1)
    with caplog.at_level(logging.WARNING, logger=compile_ebvla.__name__):
        got = graphs(energy_chain(weight), [weight], *call_inputs, None)
    assert torch.equal(got[0].actions, energy_chain(weight)(*call_inputs, None)[0].actions)
    assert "could not capture the refinement of chunks shaped (2, 4, 2)" in caplog.text
    assert list(graphs.failures.values()) == [
        "RuntimeError: operation not permitted when stream is capturing"
    ]


def test_a_cast_that_remakes_the_rotary_buffer_captures_again(recorded, monkeypatch):
    """`policy.float()` leaves fp32 parameters where they are but remakes the head's rotary frequencies: a graph
    recorded before would read their freed memory."""
    aot_eager_compiles(monkeypatch)
    clear_compiled()
    policy = make_policy(compile_mode="chunk-graph")
    batch = tiny_batch(policy.config, batch_size=BATCH_SIZE, seed=31, with_action=False)
    try:
        chunk(policy, batch)
        chunk(policy, batch)
        assert recorded.captures == 1
        policy.float()
        chunk(policy, batch)
    finally:
        clear_compiled()
    assert recorded.captures == 2
