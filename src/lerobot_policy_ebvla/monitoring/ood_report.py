"""The OOD detection report (paper Table III) on held-out rollouts, with the baselines side by side.

`OODReportConfig` is the configuration `ebvla-ood-report` parses; `write_ood_report` builds the report from
record files and writes `ood_report.md`, the figures `roc_curve.png`, `roc_baselines.png` and
`energy_histogram.png`, and on request the checkpoint's `ood_calibration.json`. Its sections: the protocol and
calibration, energy vs success drop per condition, AUROC with bootstrap 95% intervals per score, the same
AUROCs over each episode's first k chunks beside the whole episode's, each score's AUROC of failed against
successful rollouts, Table III per condition in the paper's layout with every score's balanced accuracy beside
it, and Table III again over the first k chunks. Each two-sided score sits beside its one-sided form.

`score_ood_report` is its first half, the rollouts and their scores (`OODScores`), and `write_scored_report` the
second: an analysis that needs another section (the research's score summary) scores once and adds it.

With context features, the scores include the combinations of the final energy and the context distance
(`baselines.COMBINED_SCORES`), rollout scores standardized on the calibration rollouts aggregated the same way
(over the whole episode, or over the same first k chunks).
"""

import dataclasses
import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..configuration_ebvla import EBVLAConfig
from ..configuration_groups import CONTEXT_FEATURE_SCORES, MonitorConfig
from ..runtime.calibration import (
    DEFAULT_FAILURE_CHUNKS,
    FAILURE_CALIBRATION_FILENAME,
    OOD_CALIBRATION_FILENAME,
    THRESHOLD_RULES,
    FailureCalibration,
    OODCalibration,
)
from ..runtime.scores import INPUT_SOURCES, SCORE_AGGREGATIONS, SCORES, reading_of
from ..runtime.statistics import DEFAULT_KNN_K
from .baselines import (
    COMBINED_FROM,
    COMBINED_SCORES,
    FEATURE_SCORES,
    ScoreReference,
    available_scores,
    fit_score_reference,
    recorded_inputs,
    registered_scores,
    vanilla_rollouts,
)
from .failure_check import failure_check_section
from .metrics import percent
from .ood import TABLE_III_MULTIPLIERS
from .ood_sections import (
    ALL_CONDITIONS,
    auroc_table,
    calibration_table,
    conformal_note,
    figures,
    first_chunks_section,
    outcome_section,
    saved_score_note,
    success_table,
    table_iii_sections,
)
from .protocol import check_held_out
from .records import load_episodes, resolve_record_files
from .scores import (
    aggregate_episodes,
    combined_rollout_scores,
    episode_chunk_scores,
    registered_rollout_scores,
)

logger = logging.getLogger(__name__)

# The calibration rollouts the failure check is fitted on (`OODReportConfig.failure_reference`).
FAILURE_REFERENCES = ("vanilla", "successful")


def checkpoint_monitor(checkpoint: Path | None) -> MonitorConfig | None:
    """How a pretrained_model folder is monitored (its config's `monitor`, whose unset scores a config gets from
    its training signal); None without a folder."""
    if checkpoint is None or not (Path(checkpoint) / "config.json").is_file():
        return None
    return EBVLAConfig.from_pretrained(checkpoint).monitor


def checkpoint_monitor_score(checkpoint: Path | None) -> str:
    """The score a pretrained_model folder is monitored with: its config's `monitor.score`; the paper's final
    energy without a folder."""
    monitor = checkpoint_monitor(checkpoint)
    return "final_energy" if monitor is None else monitor.score


@dataclass
class OODReportConfig:
    """Energy-based OOD detection report (Table III) on held-out rollouts, with the baselines side by side.

    Calibrate (mu_v, sigma_v of Eq. 5, the conformal threshold, the feature baselines) on `calibration`
    vanilla rollouts; report on held-out `vanilla` rollouts (the negatives) and `ood` rollouts (the
    positives, one condition per perturbation and severity their records carry). Each path is a records
    file, an eval folder or a glob pattern; lists are written `--ood='[outputs/eval/pose*,outputs/eval/fov2]'`.
    """

    # Vanilla rollouts that set mu_v, sigma_v, the conformal threshold and the feature baselines.
    calibration: list[str] = field(default_factory=list)
    # Fit on the calibration rollouts that succeeded only. A failed vanilla rollout can drift far from the
    # others (the arm astray): with few calibration rollouts it inflates sigma_v, and the context distance's
    # threshold then flags nothing (research/docs/benchmarks_history.md section 6, the sweep).
    calibration_successes_only: bool = False
    # Held-out vanilla rollouts (other seeds than the calibration's): the negatives.
    vanilla: list[str] = field(default_factory=list)
    # Perturbed rollouts: the positives, reported per (perturbation, severity) and all together.
    ood: list[str] = field(default_factory=list)
    # Allow a report set that shares files or episode seeds with `calibration`, or no `calibration` (then
    # `vanilla` calibrates): the report is labelled IN-SAMPLE. Without it such a report is refused.
    in_sample: bool = False
    # Folder for ood_report.md and the figures.
    output_dir: Path = Path("outputs/ood_report")
    # How a rollout's chunk scores form its score: mean, max, last or median.
    aggregation: str = "mean"
    # Std multipliers k of Table III's rows (T = mu_v + k sigma_v).
    multipliers: list[float] = field(default_factory=lambda: list(TABLE_III_MULTIPLIERS))
    # False-alarm rate alpha of the conformal threshold (its last row in Table III).
    false_alarm_rate: float = 0.05
    # Bootstrap resamples of the AUROC intervals.
    n_bootstrap: int = 1000
    # Seed of the bootstrap generator.
    seed: int = 0
    # Neighbours of the k-NN feature baseline (and the k a `--score=context_knn` calibration saves); 5 before
    # 2026-11-24 (runtime.statistics.DEFAULT_KNN_K says why 1).
    knn_k: int = DEFAULT_KNN_K
    # Detection on the first chunks: every score's AUROC over each episode's first k chunks, for each k,
    # beside the whole episode's (an episode shorter than k uses all its chunks).
    first_chunks: list[int] = field(default_factory=lambda: [1, 3, 5])
    # Table III once more over each episode's first k chunks, thresholds from the calibration rollouts' first
    # k chunks; 0 leaves it out.
    table_iii_first_chunks: int = 3
    # Write ood_calibration.json (`score`, fitted on `calibration`) into this pretrained_model folder.
    calibrate_to: Path | None = None
    # The chunk score the saved calibration is of (a name of `runtime.scores.SCORES`, and a row of the report).
    # None: the checkpoint's own, its config's `monitor.score`, decided when the policy was trained.
    score: str | None = None
    # k saved in the calibration.
    k: float = 1.0
    # Threshold the policy's monitor applies from the saved calibration: mean_std (Eq. 5) or conformal.
    threshold_rule: str = "mean_std"
    # The failure check's threshold rule (and its baselines' in the report). None: `threshold_rule`. A failure
    # check chosen at Eq. 5's T keeps it while the OOD threshold is the conformal quantile.
    failure_threshold_rule: str | None = None
    # The energy score of the monitor's failure check, fitted on the same calibration rollouts' first
    # `failure_chunks` chunks, reported held out against the baselines and saved as failure_calibration.json with
    # `calibrate_to`. None: the checkpoint's `monitor.failure_score`, or without a checkpoint
    # head_energy_two_sided where the records carry E_c; "none" leaves it out.
    failure_score: str | None = None
    # N, the first chunks the failure check scores. None: the checkpoint's `monitor.failure_chunks` (3).
    failure_chunks: int | None = None
    # The calibration rollouts the failure check's threshold (and each baseline's in its section) is fitted on:
    # "vanilla", all of them, or "successful", those that succeeded. A failed calibration rollout's late chunks
    # inflate sigma_v of a score that rises once a rollout goes wrong, and T then flags few failures.
    failure_reference: str = "vanilla"
    # Replace an existing ood_calibration.json (and failure_calibration.json).
    overwrite_calibration: bool = False

    @property
    def failure_rule(self) -> str:
        """The threshold rule of the failure check and of its baselines."""
        return self.threshold_rule if self.failure_threshold_rule is None else self.failure_threshold_rule

    def validate(self) -> None:
        # Not __post_init__: draccus would wrap the ValueError in a less readable ParsingError.
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        for name, rule in (
            ("threshold_rule", self.threshold_rule),
            ("failure_threshold_rule", self.failure_rule),
        ):
            if rule not in THRESHOLD_RULES:
                raise ValueError(f"`{name}` must be one of {THRESHOLD_RULES}, got {rule!r}.")
        if self.score is not None and self.score not in SCORES:
            raise ValueError(f"`score` must be one of {tuple(SCORES)}, got {self.score!r}.")
        if self.failure_score not in (None, "none") and self.failure_score not in SCORES:
            raise ValueError(
                f"`failure_score` must be 'none' or one of {tuple(SCORES)}, got {self.failure_score!r}."
            )
        if self.failure_chunks is not None and self.failure_chunks < 1:
            raise ValueError(f"`failure_chunks` must be >= 1, got {self.failure_chunks}.")
        if self.failure_reference not in FAILURE_REFERENCES:
            raise ValueError(
                f"`failure_reference` must be one of {FAILURE_REFERENCES}, got {self.failure_reference!r}."
            )
        if any(k < 1 for k in self.first_chunks) or self.table_iii_first_chunks < 0:
            raise ValueError(
                f"`first_chunks` must be >= 1 and `table_iii_first_chunks` >= 0, got {self.first_chunks} "
                f"and {self.table_iii_first_chunks}."
            )
        if not self.vanilla or not self.ood:
            raise ValueError(
                "Give held-out vanilla (`--vanilla`) and perturbed (`--ood`) rollouts to report on."
            )


def _condition_name(perturbation: str, severity: float) -> str:
    return f"{perturbation} {severity:g}" if perturbation != "none" else "unperturbed (from --ood)"


@dataclass
class ScoredSets:
    """Every score of the held-out rollouts over the same chunks: negatives, and positives per condition."""

    negatives: dict[str, np.ndarray]
    positives: dict[str, dict[str, np.ndarray]]


def _check_vanilla_only(flag: str, episodes: dict) -> None:
    perturbed = sorted(
        {f"{key.perturbation} {key.severity:g}" for _, key in episodes if key.perturbation != "none"}
    )
    if perturbed:
        raise ValueError(f"`{flag}` must hold vanilla rollouts only, but has perturbed ones: {perturbed}.")


def _conditions(ood: dict) -> dict[str, dict]:
    """All perturbed rollouts together, then one condition per (perturbation, severity)."""
    conditions: dict[str, dict] = {ALL_CONDITIONS: ood}
    for key, episode in sorted(ood.items(), key=lambda item: (item[0][1].perturbation, item[0][1].severity)):
        conditions.setdefault(_condition_name(key[1].perturbation, key[1].severity), {})[key] = episode
    return conditions


@dataclass
class OODScores:
    """A report's rollouts and every score of them (`score_ood_report`): what each section is built from.

    Each chunk is scored once (`*_chunks`: by score name, each episode's chunk scores, or a registered score's
    fitted score and chunk components); `at(k)` aggregates them over each episode's first k chunks (None: the
    whole episode), `fit(name, k)` fits the threshold statistics on the calibration rollouts aggregated alike.
    """

    cfg: OODReportConfig
    calibration_set: dict
    vanilla: dict
    ood: dict
    conditions: dict[str, dict]
    names: list[str]
    reference: ScoreReference
    saved_score: str
    failure_score: str  # "none": no failure check
    failure_chunks: int
    in_sample: bool
    n_calibration_files: int
    n_failed_left_out: int
    calibration_chunks: dict
    vanilla_chunks: dict
    condition_chunks: dict[str, dict]
    # A cache of `at`; not an argument, so that `dataclasses.replace` starts an empty one.
    _scored: dict = field(default_factory=dict, init=False, repr=False)

    def scores(self, chunks: dict, name: str, first_chunks: int | None = None) -> np.ndarray:
        """The rollout scores of one set (its chunk scores by name), over whole episodes or first chunks."""
        if name in self.reference.registered:
            return registered_rollout_scores(chunks[name], self.cfg.aggregation, first_chunks)
        if name in COMBINED_SCORES:
            # Standardized on the calibration rollouts aggregated over the same chunks.
            return combined_rollout_scores(
                name,
                {n: self.scores(chunks, n, first_chunks) for n in COMBINED_FROM},
                {n: self.scores(self.calibration_chunks, n, first_chunks) for n in COMBINED_FROM},
            )
        return aggregate_episodes(chunks[name], self.cfg.aggregation, first_chunks)

    def fit(self, name: str, first_chunks: int | None = None) -> OODCalibration:
        """The threshold statistics of a score on the calibration rollouts' scores over the same chunks."""
        return self._fit(self.scores(self.calibration_chunks, name, first_chunks), name=name)

    @cached_property
    def saved_fit(self) -> OODCalibration:
        """The OOD check `--calibrate_to` saves: the saved score's `ChunkWindow` over the calibration rollouts'
        first N = `table_iii_first_chunks` chunks and T fitted on their window scores (each leave-one-out), so that
        T bounds the alarms the run-time monitor raises at any of its first N decisions; with N = 0, the score
        fitted on whole episodes. Computed once: the report, its failure section and `--calibrate_to` all read it."""
        n = self.cfg.table_iii_first_chunks
        if not n:
            return self.fit(self.saved_score)
        running = self.running_scores(self.calibration_chunks, self.saved_score, n)
        return self._fit(running, window=True, name=self.saved_score)

    def running_scores(self, chunks: dict, name: str, window_chunks: int) -> np.ndarray:
        """(R, N) each rollout's score over its first 1, ..., N chunks (a rollout shorter than n: all its chunks)."""
        return np.stack([self.scores(chunks, name, n) for n in range(1, window_chunks + 1)], axis=1)

    def saved_scores(self, chunks: dict) -> np.ndarray:
        """The rollout scores of one set as the saved OOD check decides on them (`saved_fit`): window scores
        over the first N chunks, or whole-episode scores."""
        window = self.saved_fit.window
        if window is None:
            return self.scores(chunks, self.saved_score)
        return window.scores(self.running_scores(chunks, self.saved_score, window.chunks))

    def saved_held_out(self) -> np.ndarray:
        """`saved_scores` of every held-out rollout, in `held_out_failed`'s order."""
        return np.concatenate(
            [self.saved_scores(self.vanilla_chunks), self.saved_scores(self.condition_chunks[ALL_CONDITIONS])]
        )

    def fit_failure(self, name: str, first_chunks: int) -> OODCalibration:
        """`fit` on the failure check's reference rollouts (`failure_reference`) only."""
        return self._fit(
            self.scores(self.calibration_chunks, name, first_chunks)[self.failure_reference_mask()],
            self.cfg.failure_rule,
            name=name,
        )

    def failure_reference_mask(self) -> np.ndarray:
        """Which calibration rollouts (in `calibration_set` order) the failure check's thresholds are fitted on."""
        successful = np.array([episode[0].success for episode in self.calibration_set.values()], dtype=bool)
        if self.cfg.failure_reference == "vanilla":
            return np.ones_like(successful)
        if successful.sum() < 2:
            raise ValueError(
                f"`--failure_reference=successful` leaves {successful.sum()} successful calibration rollout(s) of "
                f"{len(successful)}: at least 2 are needed for mu_v and sigma_v."
            )
        return successful

    def _fit(
        self, calibration_scores: np.ndarray, rule: str | None = None, window: bool = False, name: str = ""
    ) -> OODCalibration:
        """The report's threshold statistics of calibration scores (of the score `name`), or with `window` of
        (R, N) running scores; aggregated as the score's own reading says where it has one."""
        fit = OODCalibration.fit_window if window else OODCalibration.fit
        return fit(
            calibration_scores,
            k=self.cfg.k,
            aggregation=reading_of(SCORES[name], self.cfg.aggregation)
            if name in SCORES
            else self.cfg.aggregation,
            false_alarm_rate=self.cfg.false_alarm_rate,
            rule=self.cfg.threshold_rule if rule is None else rule,
        )

    def held_out(self, name: str, first_chunks: int | None = None) -> np.ndarray:
        """Every held-out rollout's score, the vanilla ones first, then the perturbed ones (`held_out_failed`'s
        order)."""
        scored = self.at(first_chunks)
        return np.concatenate([scored.negatives[name], scored.positives[ALL_CONDITIONS][name]])

    def held_out_failed(self) -> np.ndarray:
        """Whether each held-out rollout failed, the vanilla ones first, then the perturbed ones."""
        episodes = [*self.vanilla.values(), *self.ood.values()]
        return np.array([not episode[0].success for episode in episodes], dtype=bool)

    def at(self, first_chunks: int | None = None) -> ScoredSets:
        """Every score of the held-out rollouts over each episode's first k chunks (None: whole episodes)."""
        if first_chunks not in self._scored:
            self._scored[first_chunks] = ScoredSets(
                {name: self.scores(self.vanilla_chunks, name, first_chunks) for name in self.names},
                {
                    c: {name: self.scores(chunks, name, first_chunks) for name in self.names}
                    for c, chunks in self.condition_chunks.items()
                },
            )
        return self._scored[first_chunks]


def score_ood_report(cfg: OODReportConfig) -> OODScores:
    """Loads the report's rollouts, fits the reference scores on the calibration rollouts and scores every chunk.

    Raises:
        ValueError: An invalid option, a refused in-sample report (`monitoring.protocol`), perturbed rollouts in
            a vanilla set, or a `--score` the records lack an input of.
    """
    cfg.validate()
    vanilla = load_episodes(cfg.vanilla)
    ood = load_episodes(cfg.ood)
    calibration_set = load_episodes(cfg.calibration) if cfg.calibration else None
    in_sample = check_held_out(calibration_set, {**vanilla, **ood}, cfg.in_sample)
    if calibration_set is None:
        calibration_set = vanilla
    n_failed_left_out = 0
    if cfg.calibration_successes_only:
        successful = {key: chunks for key, chunks in calibration_set.items() if chunks[0].success}
        n_failed_left_out = len(calibration_set) - len(successful)
        if len(successful) < 2:
            raise ValueError(
                f"`--calibration_successes_only=true` leaves {len(successful)} successful calibration rollout(s) "
                f"of {len(calibration_set)}: at least 2 are needed for mu_v and sigma_v."
            )
        calibration_set = successful
    n_calibration_files = len(resolve_record_files(cfg.calibration or cfg.vanilla))
    _check_vanilla_only("--calibration", calibration_set)
    _check_vanilla_only("--vanilla", vanilla)
    conditions = _conditions(ood)

    every_episode = [*calibration_set.values(), *vanilla.values(), *ood.values()]
    chunk_names = available_scores(every_episode)
    inputs = recorded_inputs(every_episode)
    has_features = "context_features" in inputs
    can_combine = all(name in chunk_names for name in COMBINED_FROM)
    monitor = checkpoint_monitor(cfg.calibrate_to)
    saved_score = cfg.score or checkpoint_monitor_score(cfg.calibrate_to)
    failure_score = cfg.failure_score or (
        monitor.failure_score
        if monitor is not None
        else _DEFAULT_FAILURE_SCORE
        if _DEFAULT_FAILURE_SCORE in SCORES and set(SCORES[_DEFAULT_FAILURE_SCORE].reads) <= inputs
        else "none"
    )
    if (
        monitor is not None
        and failure_score in CONTEXT_FEATURE_SCORES
        and monitor.failure_score != failure_score
    ):
        raise ValueError(
            f"`--failure_score={failure_score}` reads each chunk's pooled context, which the policy passes with its "
            f"readout only when its config names such a failure check, and {cfg.calibrate_to}'s config names "
            f"{monitor.failure_score!r}: calibrate a checkpoint saved with `monitor.failure_score={failure_score!r}`."
        )
    # A score that trains a model is computed only when it is the one saved or the failure check.
    registered = [
        n
        for n in registered_scores()
        if set(SCORES[n].reads) <= inputs
        and (not SCORES[n].trains_model or n in (saved_score, failure_score))
    ]
    names = _beside_one_sided([*chunk_names, *(COMBINED_SCORES if can_combine else ()), *registered])
    failure_chunks = cfg.failure_chunks or (
        DEFAULT_FAILURE_CHUNKS if monitor is None else monitor.failure_chunks
    )
    for option, score in (("score", saved_score), ("failure_score", failure_score)):
        if score != "none" and score not in names:
            missing = [name for name in SCORES[score].reads if name not in inputs]
            raise ValueError(
                f"`--{option}={score}` needs, in every chunk of every set, "
                + "; ".join(INPUT_SOURCES[name] for name in missing)
                + "."
            )
    reference = fit_score_reference(calibration_set, cfg.knn_k, has_features, registered, cfg.aggregation)

    # Each chunk is scored once; the whole-episode and first-chunk scores aggregate the same chunk scores (a
    # registered score's chunk components, with the fitted score of each episode).
    calibration_chunks, vanilla_chunks, ood_chunks = (
        {name: episode_chunk_scores(episodes, name, reference) for name in chunk_names}
        | {
            name: {key: model.components(episode, key) for key, episode in episodes.items()}
            for name, model in reference.registered.items()
        }
        for episodes in (calibration_set, vanilla, ood)
    )
    condition_chunks = {
        c: {name: {key: chunks[key] for key in episodes} for name, chunks in ood_chunks.items()}
        for c, episodes in conditions.items()
    }
    return OODScores(
        cfg,
        calibration_set,
        vanilla,
        ood,
        conditions,
        names,
        reference,
        saved_score,
        failure_score,
        failure_chunks,
        in_sample,
        n_calibration_files,
        n_failed_left_out,
        calibration_chunks,
        vanilla_chunks,
        condition_chunks,
    )


def write_ood_report(cfg: OODReportConfig) -> str:
    """Builds the report, writes it and the figures to `cfg.output_dir`, and returns its markdown.

    Raises:
        ValueError: An invalid option, a refused in-sample report (`monitoring.protocol`), or perturbed
            rollouts in a vanilla set.
        FileExistsError: `calibrate_to` holds a calibration and `overwrite_calibration` is False.
    """
    cfg.validate()
    for filename in (OOD_CALIBRATION_FILENAME, FAILURE_CALIBRATION_FILENAME):
        calibration_file = cfg.calibrate_to / filename if cfg.calibrate_to else None
        if calibration_file is not None and calibration_file.exists() and not cfg.overwrite_calibration:
            raise FileExistsError(
                f"{calibration_file} exists; pass `--overwrite_calibration=true` to replace it."
            )
    return write_scored_report(score_ood_report(cfg))


def write_scored_report(scored: OODScores) -> str:
    """`write_ood_report` from its scores: the report's sections, figures and the saved calibration."""
    cfg, names, vanilla, conditions = scored.cfg, scored.names, scored.vanilla, scored.conditions
    by_length = {k: scored.at(k) for k in [None, *cfg.first_chunks, cfg.table_iii_first_chunks or None]}
    fits = {name: scored.fit(name) for name in names}
    negatives, positives = by_length[None].negatives, by_length[None].positives

    label = "IN-SAMPLE (calibration and report sets overlap: optimistic)" if scored.in_sample else "held-out"
    fitted_on_calibration = [
        *(FEATURE_SCORES if scored.reference.features else ()),
        *scored.reference.registered,
    ]
    sections = [
        f"# Energy-based OOD detection ({label})",
        f"Calibration: {len(scored.calibration_set)} vanilla rollouts from {scored.n_calibration_files} record "
        "file(s)"
        + (
            f" (successful only: {scored.n_failed_left_out} failed left out). "
            if cfg.calibration_successes_only
            else ". "
        )
        + f"Report: {len(vanilla)} held-out vanilla rollouts (negatives), {len(scored.ood)} perturbed rollouts "
        f"(positives). Rollout score: {cfg.aggregation} of the chunk scores. Thresholds: T = mu + k sigma "
        f"(Eq. 5) and the conformal threshold at false-alarm rate alpha = {percent(cfg.false_alarm_rate)}. "
        f"Scores: {', '.join(names)}. Held out changes only what is fitted on the calibration rollouts: the "
        "thresholds and the reference scores (phase_energy"
        + "".join(f", {name}" for name in fitted_on_calibration)
        + "); an AUROC of the final energy needs no threshold. A calibration rollout's own reference scores "
        "are computed leave-one-episode-out.",
        "## Calibration\n\n"
        + calibration_table(fits, negatives, cfg)
        + conformal_note(fits, cfg)
        + saved_score_note(cfg, scored),
        "## Energy vs success drop (final energy)\n\n"
        + success_table(vanilla, conditions, fits, negatives, positives, cfg),
        "## AUROC [bootstrap 95% interval] by score\n\n"
        + auroc_table(conditions, names, negatives, positives, cfg),
        first_chunks_section(by_length, vanilla, conditions, names, cfg),
        outcome_section(by_length, vanilla, scored.ood, names, cfg),
        *([failure_check_section(scored)] if scored.failure_score != "none" else []),
        *table_iii_sections("Table III", fits, by_length[None], vanilla, conditions, names, cfg),
    ]
    if cfg.table_iii_first_chunks:
        k = cfg.table_iii_first_chunks
        sections.append(
            f"## Table III on the first {k} chunks\n\nThe same tables with every score over each episode's "
            f"first {k} chunks (an episode shorter than {k} uses all its chunks); mu_v, sigma_v and the "
            f"conformal threshold from the calibration rollouts' first {k} chunks."
        )
        first_fits = {name: scored.fit(name, k) for name in names}
        sections += table_iii_sections(
            f"Table III, first {k} chunks", first_fits, by_length[k], vanilla, conditions, names, cfg
        )
    report = "\n\n".join(sections) + "\n"

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "ood_report.md").write_text(report, encoding="utf-8")
    calibration_scores = scored.scores(scored.calibration_chunks, "final_energy")
    figures(cfg, fits, calibration_scores, negatives, positives, names)
    if cfg.calibrate_to is not None:
        # The run-time monitor scores chunks against a score fitted on every calibration rollout; its window,
        # mu_v and sigma_v are the report's (`saved_fit`): a T fitted on whole episodes flagged a third of vanilla
        # rollouts in their first chunks, and one fitted on N-chunk means a quarter by chunk N, through the
        # running scores of chunks 1..N-1 that spread more.
        saved = scored.saved_score
        score = SCORES[saved].fit(vanilla_rollouts(scored.calibration_set, cfg.aggregation, cfg.knn_k))
        calibration = dataclasses.replace(scored.saved_fit, score=score)
        path = calibration.save(cfg.calibrate_to, overwrite=cfg.overwrite_calibration)
        logger.info(f"Saved the OOD calibration ({saved}, T = {calibration.threshold:.3f}) to {path}")
        if scored.failure_score != "none":
            failure = _failure_calibration(scored)
            path = failure.save(cfg.calibrate_to, overwrite=cfg.overwrite_calibration)
            logger.info(
                f"Saved the failure check ({failure.score.name}, T = {failure.threshold:.3f}) to {path}"
            )
    return report


_DEFAULT_FAILURE_SCORE = "head_energy_two_sided"


def _failure_calibration(scored: OODScores) -> FailureCalibration:
    """The failure check `--calibrate_to` saves: its score fitted on every calibration rollout, mu_v and sigma_v
    those of the reference rollouts' first N chunks (`failure_reference`; leave-one-out, as the report's)."""
    cfg, name, n = scored.cfg, scored.failure_score, scored.failure_chunks
    if name in scored.reference.registered:  # fitted on every calibration rollout already
        score = scored.reference.registered[name].fitted
    else:
        score = SCORES[name].fit(vanilla_rollouts(scored.calibration_set, cfg.aggregation, cfg.knn_k))
    return FailureCalibration.of(dataclasses.replace(scored.fit_failure(name, n), score=score), n)


def _beside_one_sided(names: list[str]) -> list[str]:
    """The scores in order, each two-sided score ("<name>_two_sided") moved right after its one-sided form."""
    ordered = [n for n in names if not (n.endswith("_two_sided") and n.removesuffix("_two_sided") in names)]
    for name in names:
        if name not in ordered:
            ordered.insert(ordered.index(name.removesuffix("_two_sided")) + 1, name)
    return ordered
