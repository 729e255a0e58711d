"""Every figure of the monitoring tools: ROC curves, score histograms, energy over time, energy landscapes.

Figures are written to files only (no display on robots and CI machines), so matplotlib runs on its Agg
backend, set once here; matplotlib is imported when a figure is drawn, not when the package is imported.
"""

import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .failure import energy_matrix
from .records import Episode

if TYPE_CHECKING:
    from .landscape import EnergyLandscape


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    _pyplot().close(fig)
    return path


def plot_roc(curves: Mapping[str, tuple[np.ndarray, np.ndarray, float]], path: str | Path) -> Path:
    """Saves ROC curves, one per label: {label: (fpr, tpr, auroc)}."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 5))
    for label, (fpr, tpr, area) in curves.items():
        ax.plot(fpr, tpr, label=f"{label} (AUROC {area:.3f})")
    ax.plot([0, 1], [0, 1], color="gray", linestyle="--", linewidth=1)
    ax.set_xlabel("FPR (negatives flagged)")
    ax.set_ylabel("TPR (positives caught)")
    ax.legend(loc="lower right", fontsize="small")
    return _save(fig, path)


def plot_score_histograms(
    groups: Mapping[str, Sequence[float]], thresholds: Mapping[str, float], path: str | Path, xlabel: str
) -> Path:
    """Saves overlaid histograms of rollout scores per group, with each threshold as a vertical line."""
    plt = _pyplot()
    scores = {label: np.asarray(values, dtype=float) for label, values in groups.items()}
    # Infinite scores (diverged refinement) cannot be binned; the legend counts them instead.
    all_finite = np.concatenate([s[np.isfinite(s)] for s in scores.values()] or [np.zeros(0)])
    bins = np.histogram_bin_edges(all_finite, bins=30) if all_finite.size else 10
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, values in scores.items():
        n_inf = int(np.sum(~np.isfinite(values)))
        suffix = f", {n_inf} non-finite" if n_inf else ""
        ax.hist(values[np.isfinite(values)], bins=bins, alpha=0.5, label=f"{label} (n={values.size}{suffix})")
    for (label, threshold), style in zip(thresholds.items(), ("--", ":", "-."), strict=False):
        if np.isfinite(threshold):
            ax.axvline(threshold, color="red", linestyle=style, label=f"{label} = {threshold:.3f}")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("rollouts")
    ax.legend(fontsize="small")
    return _save(fig, path)


def plot_energy_over_time(episodes: Sequence[Episode], path: str | Path) -> Path:
    """Saves initial and final energy against chunk index: each episode faintly, each group's mean boldly."""
    plt = _pyplot()
    failed = np.array([not e[0].success for e in episodes])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharex=True)
    for ax, metric in zip(axes, ("start", "final"), strict=True):
        energies = energy_matrix(episodes, metric)  # (N, max_chunks), NaN after an episode ends
        energies[~np.isfinite(energies)] = np.nan  # +inf would swamp the axis; leave a gap instead
        for label, rows, color in (("success", ~failed, "tab:blue"), ("failure", failed, "tab:red")):
            if not rows.any():
                continue
            for series in energies[rows]:
                ax.plot(series, color=color, alpha=0.15, linewidth=0.8)
            with warnings.catch_warnings():
                # Columns past the end of every episode of the group are all NaN; their mean is NaN.
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(energies[rows], axis=0)
            ax.plot(mean, color=color, linewidth=2.5, label=f"{label} mean (n={int(rows.sum())})")
        ax.set_title(f"{'Initial' if metric == 'start' else 'Final'} energy")
        ax.set_xlabel("chunk index")
        ax.set_ylabel("energy")
        ax.legend(fontsize="small")
    return _save(fig, path)


def plot_energy_landscape(
    landscape: "EnergyLandscape", path: str | Path, kind: str = "both", title: str | None = None
) -> Path:
    """Saves the landscape as a PNG: a 3-D surface, a filled contour map, or both side by side.

    The refined action is marked with a star.

    Args:
        landscape: The output of `energy_landscape`.
        path: Destination PNG file; its folder is created.
        kind: "surface", "contour" or "both".
        title: Figure title.
    """
    if kind not in ("surface", "contour", "both"):
        raise ValueError(f"`kind` must be 'surface', 'contour' or 'both', got {kind!r}.")
    plt = _pyplot()
    grid_x, grid_y = np.meshgrid(landscape.x, landscape.y)
    # Energies can be +inf where the head diverged; mask them so the colour scale stays readable.
    energies = np.ma.masked_invalid(landscape.energies)
    x_label, y_label = (f"action[{landscape.timestep}, {d}]" for d in landscape.dims)
    kinds = ["surface", "contour"] if kind == "both" else [kind]
    fig = plt.figure(figsize=(6 * len(kinds), 5))
    for i, panel in enumerate(kinds, start=1):
        if panel == "surface":
            ax = fig.add_subplot(1, len(kinds), i, projection="3d")
            ax.plot_surface(grid_x, grid_y, energies, cmap="viridis", linewidth=0, antialiased=True)
            ax.scatter(*landscape.center, landscape.center_energy, color="red", marker="*", s=150)
            ax.set_zlabel("energy")
        else:
            ax = fig.add_subplot(1, len(kinds), i)
            contour = ax.contourf(grid_x, grid_y, energies, levels=30, cmap="viridis")
            fig.colorbar(contour, ax=ax, label="energy")
            ax.plot(*landscape.center, marker="*", color="red", markersize=14, label="refined action")
            ax.legend(loc="upper right")
        ax.set_xlabel(x_label)
        ax.set_ylabel(y_label)
    if title:
        fig.suptitle(title)
    return _save(fig, path)
