"""research/benchmarks/window_monitor_on_records.py on the committed records of
research/results/metaworld_sweep_margin_full."""

from research.tests.conftest import RESULTS, load_benchmark


def test_window_monitor_flags_every_window_of_a_mild_shift_the_rollouts_pass_alone(capsys):
    example = load_benchmark("window_monitor_on_records")
    example.main(example.WindowExampleConfig())
    printed = capsys.readouterr().out
    # 24 fresh rollouts under mild noise: 7 before the first decision, then 17 windows, every one atypical.
    assert printed.count("no decision yet") == 7
    assert "17 of 17 windows atypical at alpha = 0.05" in printed and "-> shifted" in printed

    fresh = RESULTS / "metaworld_sweep_margin_full" / "seed12000" / "observation"
    example.main(example.WindowExampleConfig(rollouts=fresh / "context_energy_fresh" / "vanilla"))
    assert "3 of 93 windows atypical" in capsys.readouterr().out  # fresh vanilla rollouts of the same policy
