"""The window typicality test (`window_monitor.py`) on sweeps of recorded rollouts, one section per run.

A run is a sweep folder of `metaworld_perturbation_sweep.py` records (`calibration/`, `vanilla/`, one folder per
condition; `vanilla_extra/` left out), optionally with a folder of fresh rollouts:

- `NAME=SWEEP`: the sweep's vanilla rollouts are split in episode order, the first half the test's reference
  (scored against the calibration's fit, `window_report.window_values_of`), the second half the
  held-out vanilla whose windows are the false alarms; the conditions are the sweep's.
- `NAME=SWEEP,FRESH`: every sweep vanilla rollout is the reference; FRESH's `vanilla/` is the held-out vanilla;
  the conditions are the sweep's and FRESH's other folders (fresh rollouts of some of them, named `fresh <c>`).
  With M reference rollouts the test's false-alarm rate is alpha over draws of the reference, not for each
  one: 20 gave 1-42% on eight training seeds, 40 gave 4-7% on five (research/docs/window_test.md).

Every score is over each episode's first `--first_chunks` chunks (3: what a monitor has seen early on).

    python research/benchmarks/window_typicality.py --runs s16000=$F/seed16000/observation/context_energy_full \
        --score=context_energy_two_sided --output=window.md
"""

import argparse
from pathlib import Path

import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)
from score_summaries import NOT_CONDITIONS
from window_monitor import DEFAULT_WINDOW, DEFAULT_WINDOW_FALSE_ALARM_RATE, WindowTypicalityTest
from window_report import DEFAULT_MAX_WINDOWS, score_sets, window_table

from lerobot_policy_ebvla.monitoring.records import load_episodes


def episodes_in(folder: Path) -> dict:
    """A folder's episodes in episode order."""
    episodes = load_episodes([str(folder)])
    return {key: episodes[key] for key in sorted(episodes, key=lambda k: (k[0], k[1].episode_index))}


def conditions_in(folder: Path) -> dict:
    """Each condition folder's episodes, by folder name."""
    return {
        p.name: episodes_in(p)
        for p in sorted(folder.iterdir())
        if p.is_dir() and p.name not in NOT_CONDITIONS
    }


def tested_values(test: WindowTypicalityTest) -> str:
    """What the window tests of each rollout."""
    if len(test.reference[0]) > 1:
        return "each of the score |a| and its signed aggregate a at alpha / 2"
    return "the score alone"


def run_section(
    name: str,
    sweep: Path,
    fresh: Path | None = None,
    score: str = "context_energy_two_sided",
    first_chunks: int = 3,
    window: int = DEFAULT_WINDOW,
    false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE,
    max_windows: int = DEFAULT_MAX_WINDOWS,
    n_bootstrap: int = 1000,
    score_only: bool = False,
) -> str:
    """One run's section: how it was split, then `window_report.window_table`. `score_only` tests the rollout
    score alone, not a two-sided score's signed aggregate beside it (the window test's first form)."""
    vanilla = episodes_in(sweep / "vanilla")
    conditions = conditions_in(sweep)
    if fresh is None:
        keys = list(vanilla)
        half = len(keys) // 2
        reference = {k: vanilla[k] for k in keys[:half]}
        held_out = {k: vanilla[k] for k in keys[half:]}
        protocol = f"reference: the sweep's vanilla episodes 1-{half}; held out: {half + 1}-{len(keys)}"
    else:
        reference, held_out = vanilla, episodes_in(fresh / "vanilla")
        conditions |= {f"fresh {c}": episodes for c, episodes in conditions_in(fresh).items()}
        protocol = "reference: every sweep vanilla episode; held out: the fresh vanilla episodes"

    calibration, scored = score_sets(
        episodes_in(sweep / "calibration"),
        {"reference": reference, "held_out": held_out, **conditions},
        score,
        first_chunks,
    )
    if score_only:
        for scored_set in scored.values():
            scored_set.values = scored_set.values[:, :1]
    test = WindowTypicalityTest(scored["reference"].values, window, false_alarm_rate)
    table = window_table(
        test,
        calibration.threshold,
        scored["held_out"],
        {c: scored[c] for c in conditions},
        max_windows,
        n_bootstrap,
    )
    return (
        f"## {name}\n\n`{score}` over the first {first_chunks} chunks; calibration: "
        f"{calibration.n_rollouts} rollouts (T = mu_v + sigma_v = {calibration.threshold:.3f}); {protocol} "
        f"({len(reference)} / {len(held_out)}); windows of {window} at alpha = {false_alarm_rate}, "
        f"{tested_values(test)}.\n\n"
        f"{table}\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", required=True, help="NAME=SWEEP_DIR[,FRESH_DIR]")
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--score", default="context_energy_two_sided")
    parser.add_argument("--first_chunks", type=int, default=3)
    parser.add_argument("--window", type=int, default=DEFAULT_WINDOW)
    parser.add_argument("--false_alarm_rate", type=float, default=DEFAULT_WINDOW_FALSE_ALARM_RATE)
    parser.add_argument("--max_windows", type=int, default=DEFAULT_MAX_WINDOWS)
    parser.add_argument("--n_bootstrap", type=int, default=1000)
    parser.add_argument(
        "--score_only", action="store_true", help="test the rollout score alone (the first form of the test)"
    )
    args = parser.parse_args()
    sections = []
    for run in args.runs:
        name, folders = run.split("=", 1)
        sweep, _, fresh = folders.partition(",")
        sections.append(
            run_section(
                name,
                Path(sweep),
                Path(fresh) if fresh else None,
                args.score,
                args.first_chunks,
                args.window,
                args.false_alarm_rate,
                args.max_windows,
                args.n_bootstrap,
                args.score_only,
            )
        )
    args.output.write_text("\n".join(sections))
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
