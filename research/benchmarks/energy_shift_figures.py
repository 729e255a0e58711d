"""Figures of `energy_shift_diagnosis.py`'s JSON: energy along the episode, and paired shifts per condition.

python research/benchmarks/energy_shift_figures.py --diagnosis=diag.json --output_prefix=research/docs/figures/energy_shift
"""

import argparse
import gzip
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

QUANTITIES = ("final_energy", "expert_energy", "initial_energy", "prior_energy", "rise_0.3")


def ci(values: np.ndarray, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = [values[rng.integers(0, len(values), len(values))].mean() for _ in range(1000)]
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--diagnosis", required=True)
    parser.add_argument("--output_prefix", required=True)
    parser.add_argument(
        "--along", nargs="+", default=["none_s0", "light_dim_s5", "light_color_s5", "blank_s5"]
    )
    parser.add_argument("--title", default="")
    args = parser.parse_args()
    opener = gzip.open if args.diagnosis.endswith(".gz") else open
    with opener(args.diagnosis, "rt") as f:
        data = json.load(f)["conditions"]
    names = list(data)
    vanilla = data[names[0]]

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, quantity, label in zip(
        axes, ("final_energy", "expert_energy"), ("E(a^(K), C), refined", "E(a*, C), expert"), strict=True
    ):
        for name in args.along:
            row = data[name]
            frames = np.asarray(row["frame_index"])
            values = np.asarray(row[quantity])
            xs = sorted(set(frames.tolist()))
            means = [values[frames == x].mean() for x in xs]
            bands = [ci(values[frames == x]) for x in xs]
            ax.plot(xs, means, marker="o", ms=3, label=name)
            ax.fill_between(xs, [b[0] for b in bands], [b[1] for b in bands], alpha=0.15)
        ax.axvspan(-1, 17, color="grey", alpha=0.08)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("frame of the expert episode (grey: the first 3 chunks)", fontsize=8)
    axes[0].set_ylabel("energy")
    axes[0].legend(fontsize=7)
    fig.suptitle(args.title or "mean over episodes, bootstrap 95% band", fontsize=9)
    fig.tight_layout()
    fig.savefig(f"{args.output_prefix}_along_episode.png", dpi=80)

    index = {k: i for i, k in enumerate(zip(vanilla["episode_index"], vanilla["frame_index"], strict=True))}
    fig, ax = plt.subplots(figsize=(9, 3.2))
    width = 0.8 / len(QUANTITIES)
    for q, quantity in enumerate(QUANTITIES):
        means, lows, highs = [], [], []
        for name in names[1:]:
            row = data[name]
            pairs = [
                (i, index[k])
                for i, k in enumerate(zip(row["episode_index"], row["frame_index"], strict=True))
                if k in index and k[1] <= 16
            ]
            idx, vidx = map(np.asarray, zip(*pairs, strict=True))
            d = np.asarray(row[quantity])[idx] - np.asarray(vanilla[quantity])[vidx]
            low, high = ci(d)
            means.append(d.mean())
            lows.append(d.mean() - low)
            highs.append(high - d.mean())
        xs = np.arange(len(names) - 1) + q * width
        ax.bar(xs, means, width, yerr=[lows, highs], label=quantity, capsize=2)
    ax.axhline(0, color="black", lw=0.5)
    ax.set_xticks(np.arange(len(names) - 1) + 0.4 - width / 2)
    ax.set_xticklabels(names[1:], fontsize=7, rotation=15)
    ax.set_ylabel("condition minus vanilla")
    ax.set_title(
        "paired by seed and frame, first 3 chunks (frames 0, 8, 16; n = 12 per condition)", fontsize=9
    )
    ax.legend(fontsize=7, ncol=5)
    fig.tight_layout()
    fig.savefig(f"{args.output_prefix}_paired.png", dpi=80)


if __name__ == "__main__":
    main()
