"""The OOD detection report (paper Table III) on held-out rollouts, with the baselines side by side.

`OODReportConfig` is the configuration `ebvla-ood-report` parses; `write_ood_report` builds the report from
record files and writes `ood_report.md`, the figures `roc_curve.png`, `roc_baselines.png` and
`energy_histogram.png`, and on request the checkpoint's `ood_calibration.json`. Its sections: the protocol and
calibration, energy vs success drop per condition, AUROC with bootstrap 95% intervals per score, the same
AUROCs over each episode's first k chunks beside the whole episode's, each score's AUROC of failed against
successful rollouts, a summary of every score (pooled AUROC, its worst and inverted conditions, the conditions
that cut success, failed vs successful, and the alarm rate at T = mu_v + k sigma_v beside each AUROC), Table III
per condition in the paper's layout with every score's balanced accuracy beside it, and Table III again over the
first k chunks. Each two-sided score sits beside its one-sided form.

With context features, the scores include the combinations of the final energy and the context distance
(`baselines.COMBINED_SCORES`), rollout scores standardized on the calibration rollouts aggregated the same way
(over the whole episode, or over the same first k chunks).
"""

import dataclasses
import json
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..configuration_ebvla import upgrade_legacy_fields
from ..configuration_groups import JointEnergyConfig
from ..runtime.calibration import OOD_CALIBRATION_FILENAME, THRESHOLD_RULES, OODCalibration
from ..runtime.scores import INPUT_SOURCES, SCORE_AGGREGATIONS, SCORES
from ..runtime.statistics import DEFAULT_KNN_K
from .baselines import (
    COMBINED_FROM,
    COMBINED_SCORES,
    FEATURE_SCORES,
    available_scores,
    fit_score_reference,
    recorded_inputs,
    registered_scores,
    vanilla_rollouts,
)
from .metrics import (
    BinaryRates,
    auroc,
    markdown_table,
    percent,
    roc_curve,
)
from .ood import (
    TABLE_III_MULTIPLIERS,
    format_balanced_accuracy_table,
    format_table_iii,
    ood_detection_table,
)
from .plots import plot_roc, plot_score_histograms
from .protocol import check_held_out
from .records import load_episodes, resolve_record_files
from .score_summary import (
    ALL_CONDITIONS,
    auroc_interval,
    chunks_label,
    success_rate,
    successes,
    summary_section,
)
from .scores import (
    aggregate_episodes,
    combined_rollout_scores,
    episode_chunk_scores,
    registered_rollout_scores,
)
from .window_report import window_values_of

logger = logging.getLogger(__name__)

# The score `--calibrate_to` saves without `--score`: the best held out on the MetaWorld sweep of every
# perturbation (benchmarks/results/metaworld_two_sided_scores/summary.md): the highest pooled AUROC over the
# first 3 chunks among the scores no condition is confidently inverted for (its bootstrap 95% interval wholly
# below 0.5). It reads the pooled context; records without it get the best energy-only score by the same rule.
DEFAULT_SCORE = "context_knn"
DEFAULT_ENERGY_SCORE = "phase_energy_two_sided"
# ... unless the checkpoint's joint energy has its own encoder (`joint_energy.target="observation"`): its context
# term E_c, two-sided against the vanilla E_c at each chunk index, pools 0.91-0.99 over the first 3 chunks on the
# sweeps of eight training seeds, above the final energy's 0.87-0.95 on every one, with 0-2% alarms on held-out
# vanilla (the final energy 5-25%). Neither is never wrong: each is confidently inverted on one seed's sweep, and
# on fresh rollouts E_c under three mild shifts that cost no success (benchmarks/results/metaworld_sweep_margin_full/
# summary.md, "The run-time context-energy score" to "Fresh rollouts of the default's near misses"). Records
# without E_c (a recorder before 2026-11-26) keep the final energy, which beats the context k-NN there (0.91-0.95
# against 0.77-0.92 on five seeds).
DEFAULT_JOINT_ENERGY_SCORE = "context_energy_two_sided"
JOINT_ENERGY_WITHOUT_CONTEXT_ENERGY = "final_energy"
# ... and where E_c was trained flat at the data (`joint_energy.gradient_penalty` > 0), every shift of the sweep
# raises it in every scene, and its one-sided form at each chunk index is the matched test: on four training
# seeds (two of them trained after the rule was written) it sees every success-cutting shift and is confidently
# inverted nowhere, where the two-sided form is on one (summary.md, "E_c flat at the data").
DEFAULT_FLAT_CONTEXT_ENERGY_SCORE = "context_phase_energy"


def checkpoint_fields(checkpoint: Path | None) -> dict:
    """The fields of a pretrained_model folder's config.json, in today's nested form; empty without one."""
    config = None if checkpoint is None else Path(checkpoint) / "config.json"
    if config is None or not config.is_file():
        return {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # loading the policy warns about a legacy config
        return upgrade_legacy_fields(json.loads(config.read_text()))


def _on_own_encoder(fields: dict) -> bool:
    return JointEnergyConfig(**fields.get("joint_energy", {})).on_own_encoder


def joint_energy_on_own_encoder(checkpoint: Path | None) -> bool:
    """Whether the pretrained_model folder's policy was trained with the joint energy on its own encoder."""
    return _on_own_encoder(checkpoint_fields(checkpoint))


def default_score(cfg: "OODReportConfig", inputs: set[str]) -> str:
    """The score `--calibrate_to` saves without `--score`, given the `ChunkInputs` every record has."""
    fields = checkpoint_fields(cfg.calibrate_to)
    if _on_own_encoder(fields):
        if "context_energy" not in inputs:
            return JOINT_ENERGY_WITHOUT_CONTEXT_ENERGY
        penalty = fields["joint_energy"].get("gradient_penalty", 0.0)
        return DEFAULT_FLAT_CONTEXT_ENERGY_SCORE if penalty > 0 else DEFAULT_JOINT_ENERGY_SCORE
    return DEFAULT_SCORE if "context_features" in inputs else DEFAULT_ENERGY_SCORE


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
    # threshold then flags nothing (BENCHMARKS.md section 6, the sweep).
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
    # The score summary's early window: every score over each episode's first k chunks beside the whole episode.
    summary_first_chunks: int = 3
    # Write ood_calibration.json (`score`, fitted on `calibration`) into this pretrained_model folder.
    calibrate_to: Path | None = None
    # The chunk score the saved calibration is of, a name of `runtime.scores.SCORES` and a row of the report.
    # None (default): context_knn, the best held out on the MetaWorld sweep (pooled first-3-chunk AUROC 0.842,
    # no condition confidently inverted; the final energy 0.585, confidently inverted under dim light), or
    # phase_energy_two_sided when the records have no context features, context_energy_two_sided when the
    # checkpoint's joint energy has its own encoder (`joint_energy.target="observation"`; final_energy for records
    # without `context_energy`), context_phase_energy when its E_c was also trained flat at the data
    # (`joint_energy.gradient_penalty` > 0). final_energy is the paper's score;
    # phase_energy the final energy against the calibration rollouts' at the same chunk index;
    # final_energy_two_sided and phase_energy_two_sided their |z|, high on either side of the vanilla band;
    # context_distance the chunk's pooled context against the calibration contexts (Mahalanobis);
    # energy_and_context the larger of the final energy and the context distance, each standardized on the
    # calibration rollouts; context_knn the chunk's standardized pooled context against its knn_k-th nearest
    # calibration context (saves every calibration context beside the JSON); energy_two_sided_and_context_knn
    # the larger of the two-sided phase energy and the context k-NN distance, standardized; context_energy the
    # joint energy's context term E_c, context_phase_energy its z against the calibration rollouts' E_c at the same
    # chunk index and context_energy_two_sided that z's magnitude. The context scores need records with context
    # features, the context-energy scores records of a joint-energy policy.
    score: str | None = None
    # k saved in the calibration.
    k: float = 1.0
    # Threshold the policy's monitor applies from the saved calibration: mean_std (Eq. 5) or conformal.
    threshold_rule: str = "mean_std"
    # Replace an existing ood_calibration.json.
    overwrite_calibration: bool = False

    def validate(self) -> None:
        # Not __post_init__: draccus would wrap the ValueError in a less readable ParsingError.
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        if self.threshold_rule not in THRESHOLD_RULES:
            raise ValueError(
                f"`threshold_rule` must be one of {THRESHOLD_RULES}, got {self.threshold_rule!r}."
            )
        if self.score is not None and self.score not in SCORES:
            raise ValueError(f"`score` must be one of {tuple(SCORES)}, got {self.score!r}.")
        if self.summary_first_chunks < 1:
            raise ValueError(f"`summary_first_chunks` must be >= 1, got {self.summary_first_chunks}.")
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
class _Scored:
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


def write_ood_report(cfg: OODReportConfig) -> str:
    """Builds the report, writes it and the figures to `cfg.output_dir`, and returns its markdown.

    Raises:
        ValueError: An invalid option, a refused in-sample report (`monitoring.protocol`), or perturbed
            rollouts in a vanilla set.
        FileExistsError: `calibrate_to` holds a calibration and `overwrite_calibration` is False.
    """
    cfg.validate()
    calibration_file = cfg.calibrate_to / OOD_CALIBRATION_FILENAME if cfg.calibrate_to else None
    if calibration_file is not None and calibration_file.exists() and not cfg.overwrite_calibration:
        raise FileExistsError(
            f"{calibration_file} exists; pass `--overwrite_calibration=true` to replace it."
        )
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
    registered = [n for n in registered_scores() if set(SCORES[n].reads) <= inputs]
    names = _beside_one_sided([*chunk_names, *(COMBINED_SCORES if can_combine else ()), *registered])
    saved_score = cfg.score or default_score(cfg, inputs)
    if saved_score not in names:
        missing = [name for name in SCORES[saved_score].reads if name not in inputs]
        raise ValueError(
            f"`--score={saved_score}` needs, in every chunk of every set, "
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

    def scores(chunks: dict, name: str, first_chunks: int | None = None) -> np.ndarray:
        """The rollout scores of one set (its chunk scores by name), over whole episodes or first chunks."""
        if name in reference.registered:
            return registered_rollout_scores(chunks[name], cfg.aggregation, first_chunks)
        if name in COMBINED_SCORES:
            # Standardized on the calibration rollouts aggregated over the same chunks.
            return combined_rollout_scores(
                name,
                {n: scores(chunks, n, first_chunks) for n in COMBINED_FROM},
                {n: scores(calibration_chunks, n, first_chunks) for n in COMBINED_FROM},
            )
        return aggregate_episodes(chunks[name], cfg.aggregation, first_chunks)

    def fit(name: str, first_chunks: int | None = None) -> OODCalibration:
        calibration_scores = scores(calibration_chunks, name, first_chunks)
        return OODCalibration.fit(
            calibration_scores,
            k=cfg.k,
            aggregation=cfg.aggregation,
            false_alarm_rate=cfg.false_alarm_rate,
            rule=cfg.threshold_rule,
        )

    scored: dict[int | None, _Scored] = {}
    for first_chunks in [
        None,
        *cfg.first_chunks,
        cfg.table_iii_first_chunks or None,
        cfg.summary_first_chunks,
    ]:
        if first_chunks not in scored:
            scored[first_chunks] = _Scored(
                {name: scores(vanilla_chunks, name, first_chunks) for name in names},
                {
                    c: {name: scores(chunks, name, first_chunks) for name in names}
                    for c, chunks in condition_chunks.items()
                },
            )
    fits = {name: fit(name) for name in names}
    negatives, positives = scored[None].negatives, scored[None].positives

    label = "IN-SAMPLE (calibration and report sets overlap: optimistic)" if in_sample else "held-out"
    sections = [
        f"# Energy-based OOD detection ({label})",
        f"Calibration: {len(calibration_set)} vanilla rollouts from {n_calibration_files} record file(s)"
        + (
            f" (successful only: {n_failed_left_out} failed left out). "
            if cfg.calibration_successes_only
            else ". "
        )
        + f"Report: {len(vanilla)} held-out vanilla rollouts (negatives), {len(ood)} perturbed rollouts "
        f"(positives). Rollout score: {cfg.aggregation} of the chunk scores. Thresholds: T = mu + k sigma "
        f"(Eq. 5) and the conformal threshold at false-alarm rate alpha = {percent(cfg.false_alarm_rate)}. "
        f"Scores: {', '.join(names)}. Held out changes only what is fitted on the calibration rollouts: the "
        "thresholds and the reference scores (phase_energy"
        + "".join(f", {name}" for name in [*(FEATURE_SCORES if reference.features else ()), *registered])
        + "); an AUROC of the final energy needs no threshold. A calibration rollout's own reference scores "
        "are computed leave-one-episode-out.",
        "## Calibration\n\n"
        + _calibration_table(fits, negatives, cfg)
        + _conformal_note(fits, cfg)
        + _saved_score_note(cfg, saved_score),
        "## Energy vs success drop (final energy)\n\n"
        + _success_table(vanilla, conditions, fits, negatives, positives, cfg),
        "## AUROC [bootstrap 95% interval] by score\n\n"
        + _auroc_table(conditions, names, negatives, positives, cfg),
        _first_chunks_section(scored, vanilla, conditions, names, cfg),
        _outcome_section(scored, vanilla, ood, names, cfg),
        summary_section(
            scored,
            {None: fits, cfg.summary_first_chunks: {n: fit(n, cfg.summary_first_chunks) for n in names}},
            vanilla,
            ood,
            conditions,
            names,
            cfg,
        ),
        *_table_iii_sections("Table III", fits, scored[None], vanilla, conditions, names, cfg),
    ]
    if cfg.table_iii_first_chunks:
        k = cfg.table_iii_first_chunks
        sections.append(
            f"## Table III on the first {k} chunks\n\nThe same tables with every score over each episode's "
            f"first {k} chunks (an episode shorter than {k} uses all its chunks); mu_v, sigma_v and the "
            f"conformal threshold from the calibration rollouts' first {k} chunks."
        )
        first_fits = {name: fit(name, k) for name in names}
        sections += _table_iii_sections(
            f"Table III, first {k} chunks", first_fits, scored[k], vanilla, conditions, names, cfg
        )
    report = "\n\n".join(sections) + "\n"

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "ood_report.md").write_text(report, encoding="utf-8")
    _figures(cfg, fits, scores(calibration_chunks, "final_energy"), negatives, positives, names)
    if cfg.calibrate_to is not None:
        # The run-time monitor scores chunks against a score fitted on every calibration rollout; mu_v and
        # sigma_v are the report's: the calibration rollouts' scores, leave-one-episode-out where the score
        # is fitted on them, as a new rollout's would be.
        score = SCORES[saved_score].fit(vanilla_rollouts(calibration_set, cfg.aggregation, cfg.knn_k))
        calibration = dataclasses.replace(fits[saved_score], score=score)
        # The held-out vanilla rollouts' window values against that fit are the window test's reference; vanilla
        # rollouts that are also the calibration's (in-sample) score lower than new ones would.
        if cfg.calibration and not in_sample:
            reference = window_values_of(calibration, vanilla)
            reference = reference[np.isfinite(reference).all(axis=1)]
            calibration = dataclasses.replace(calibration, window_reference=reference)
        path = calibration.save(cfg.calibrate_to, overwrite=cfg.overwrite_calibration)
        logger.info(f"Saved the OOD calibration ({saved_score}, T = {calibration.threshold:.3f}) to {path}")
    return report


def _beside_one_sided(names: list[str]) -> list[str]:
    """The scores in order, each two-sided score ("<name>_two_sided") moved right after its one-sided form."""
    ordered = [n for n in names if not (n.endswith("_two_sided") and n.removesuffix("_two_sided") in names)]
    for name in names:
        if name not in ordered:
            ordered.insert(ordered.index(name.removesuffix("_two_sided")) + 1, name)
    return ordered


def _saved_score_note(cfg: OODReportConfig, saved_score: str) -> str:
    """Which score a calibration saved by this report is of, and which table rows it is."""
    default = ""
    if cfg.score is None and cfg.calibrate_to is not None:
        if saved_score == DEFAULT_SCORE:
            why = f"`{DEFAULT_SCORE}`, the best held out on the MetaWorld sweep (docs/monitoring.md)."
        elif saved_score == DEFAULT_JOINT_ENERGY_SCORE:
            why = (
                "the checkpoint's joint energy has its own encoder, and its context term, two-sided at each chunk "
                "index, is the safest score there (docs/monitoring.md)."
            )
        elif saved_score == DEFAULT_FLAT_CONTEXT_ENERGY_SCORE:
            why = (
                "the checkpoint's context term was trained flat at the data (`joint_energy.gradient_penalty`), so "
                "every shift raises it, and its one-sided form at each chunk index is the safest score there "
                "(docs/monitoring.md)."
            )
        elif saved_score == JOINT_ENERGY_WITHOUT_CONTEXT_ENERGY and joint_energy_on_own_encoder(
            cfg.calibrate_to
        ):
            why = (
                "the checkpoint's joint energy has its own encoder, but these records hold no `context_energy` "
                f"for `{DEFAULT_JOINT_ENERGY_SCORE}` (record them again with this version): the final energy."
            )
        else:
            why = f"these records have no context features, so the best energy-only score, not `{DEFAULT_SCORE}`."
        default = f"\n\nWithout `--score`, `--calibrate_to` saves `{saved_score}`: " + why
    what = {
        "context_distance": "of every table: the same features, fit and leave-one-episode-out calibration scores.",
        "context_knn": f"of every table (k = {cfg.knn_k}): the same features, standardization and "
        "leave-one-episode-out calibration scores; the saved calibration keeps every calibration context.",
        "energy_and_context": "of the whole-episode tables: the final energy and the `context_distance` "
        "score, standardized by the calibration rollouts' mean and std of each, and their max.",
    }
    if saved_score not in what:
        return default
    return default + (
        f"\n\n`--score={saved_score}`, the score a calibration saved by this report has `ood_response` act on, is "
        f"the `{saved_score}` score {what[saved_score]}"
    )


def _first_chunks_section(scored, vanilla, conditions, names, cfg) -> str:
    lengths = [k for k in scored if k is not None and k in cfg.first_chunks]
    lines = [
        "## Detection on the first chunks: AUROC [bootstrap 95% interval]\n\n"
        "Every score over each episode's first k chunks only (an episode shorter than k uses all its "
        "chunks): what a monitor has seen k chunks into an episode, before a failure that follows the "
        "condition. "
        f"Held-out vanilla rollouts (the negatives): {len(vanilla)}, success {successes(vanilla)}."
    ]
    headers = ["Score", *(chunks_label(k) for k in lengths), chunks_label(None)]
    for condition, episodes in conditions.items():
        rows = [
            [
                name,
                *(
                    auroc_interval(scored[k].negatives[name], scored[k].positives[condition][name], cfg)
                    for k in [*lengths, None]
                ),
            ]
            for name in names
        ]
        lines.append(
            f"### {condition}: {len(episodes)} perturbed rollouts, success {successes(episodes)}\n\n"
            + markdown_table(headers, rows)
        )
    return "\n\n".join(lines)


REFERENCE_PERTURBED = "reference: perturbed or not"
REFERENCE_CONDITION_FAILURES = "reference: its condition's failure rate"


def _outcome_section(scored, vanilla, ood, names, cfg) -> str:
    """Every score's AUROC of failed (positives) against successful rollouts, per set that has both."""
    lengths = [k for k in scored if k is not None and k in cfg.first_chunks]
    vanilla_failed = np.array([not e[0].success for e in vanilla.values()], dtype=bool)
    ood_failed = np.array([not e[0].success for e in ood.values()], dtype=bool)
    # Labels, not scores: what a detector that knew them would reach (see the section's text).
    ood_failure_rates = condition_failure_rates(ood)
    vanilla_failure_rate = np.full(len(vanilla), vanilla_failed.mean() if len(vanilla) else 0.0)
    sets = {
        "held-out vanilla rollouts": (vanilla_failed, lambda s, name: s.negatives[name], {}),
        "perturbed rollouts, all conditions": (
            ood_failed,
            lambda s, name: s.positives[ALL_CONDITIONS][name],
            {REFERENCE_CONDITION_FAILURES: ood_failure_rates},
        ),
        "held-out vanilla and perturbed rollouts together": (
            np.concatenate([vanilla_failed, ood_failed]),
            lambda s, name: np.concatenate([s.negatives[name], s.positives[ALL_CONDITIONS][name]]),
            {
                REFERENCE_PERTURBED: np.concatenate([np.zeros(len(vanilla)), np.ones(len(ood))]),
                REFERENCE_CONDITION_FAILURES: np.concatenate([vanilla_failure_rate, ood_failure_rates]),
            },
        ),
    }
    lines = [
        "## Failed vs successful rollouts: AUROC [bootstrap 95% interval]\n\n"
        "Every score as a failure detector: positives are the failed rollouts, negatives the successful ones "
        "of the same set, over each episode's first k chunks and the whole episode (a failed episode runs "
        "longer, so its whole-episode score also sees its late, stalled chunks). Among perturbed rollouts a "
        "score that flags the perturbations with the most failures ranks failures high even if it knows "
        "nothing of failure within a condition: the vanilla set alone is the cleaner test. The reference rows "
        "say how far that goes: they are not scores but the rollouts' own labels, what a detector that knew "
        f"them would reach. `{REFERENCE_PERTURBED}` is a perfect OOD detector; "
        f"`{REFERENCE_CONDITION_FAILURES}` ranks each rollout by the share of its set's rollouts that failed "
        "(vanilla's, or its condition's), the most any score that knows nothing within a condition can reach."
    ]
    headers = ["Score", *(chunks_label(k) for k in lengths), chunks_label(None)]
    for title, (failed, of, references) in sets.items():
        if failed.all() or not failed.any():
            lines.append(f"### {title}: {int(failed.sum())} of {failed.size} failed, no AUROC")
            continue
        rows = [
            [
                name,
                *(
                    auroc_interval(of(scored[k], name)[~failed], of(scored[k], name)[failed], cfg)
                    for k in [*lengths, None]
                ),
            ]
            for name in names
        ]
        rows += [
            [f"_{name}_", *(auroc_interval(labels[~failed], labels[failed], cfg) for _ in [*lengths, None])]
            for name, labels in references.items()
        ]
        lines.append(
            f"### {title}: {int(failed.sum())} of {failed.size} failed\n\n" + markdown_table(headers, rows)
        )
    return "\n\n".join(lines)


def condition_failure_rates(ood: dict) -> np.ndarray:
    """Each perturbed rollout's condition's share of failed rollouts, in `ood`'s order: the failed-vs-successful
    ranking of a detector that knows every condition's outcome and nothing within a condition."""
    failed: dict[tuple[str, float], list[bool]] = {}
    for (_, key), episode in ood.items():
        failed.setdefault((key.perturbation, key.severity), []).append(not episode[0].success)
    return np.array([np.mean(failed[(key.perturbation, key.severity)]) for _, key in ood], dtype=float)


def _table_iii_sections(title, fits, scored, vanilla, conditions, names, cfg) -> list[str]:
    """Per condition: the final energy's Table III as the paper prints it, then every score's balanced
    accuracy at the same rules."""
    sections = []
    for condition, episodes in conditions.items():
        negatives, positives = scored.negatives, scored.positives[condition]
        rows = {
            name: ood_detection_table(negatives[name], positives[name], cfg.multipliers, fits[name])
            for name in names
        }
        final = "final_energy"
        sections.append(
            f"## {title}: {condition} ({len(vanilla)} vanilla vs {len(episodes)} perturbed rollouts)\n\n"
            + format_table_iii(
                rows[final],
                fits[final],
                auroc_interval(negatives[final], positives[final], cfg),
                len(vanilla),
                len(episodes),
            )
            + "\n\nBalanced accuracy of every score at the same rules:\n\n"
            + format_balanced_accuracy_table(rows)
        )
    return sections


def _calibration_table(fits: dict, negatives: dict, cfg: OODReportConfig) -> str:
    rows = []
    for name, fit in fits.items():
        t_k = fit.with_k(cfg.k).threshold
        rows.append(
            [
                name,
                fit.n_rollouts,
                f"{fit.mu_v:.4g}",
                f"{fit.sigma_v:.4g}",
                f"{t_k:.4g}",
                percent(BinaryRates.from_scores(negatives[name], [], t_k).fpr),
                f"{fit.conformal_threshold:.4g}",
                percent(BinaryRates.from_scores(negatives[name], [], fit.conformal_threshold).fpr),
            ]
        )
    headers = [
        "Score",
        "Rollouts",
        "mu",
        "sigma",
        f"T (k={cfg.k:g})",
        "Held-out FPR",
        f"T conformal (α={percent(cfg.false_alarm_rate)})",
        "Held-out FPR (conformal)",
    ]
    return markdown_table(headers, rows)


def _conformal_note(fits: dict, cfg: OODReportConfig) -> str:
    if np.isfinite(fits["final_energy"].conformal_threshold):
        return ""
    needed = math.ceil(1 / cfg.false_alarm_rate - 1 - 1e-9)
    return (
        f"\n\nThe conformal threshold is +inf (nothing flagged): alpha = {percent(cfg.false_alarm_rate)} needs "
        f"at least {needed} calibration rollouts, {fits['final_energy'].n_rollouts} were given."
    )


def _success_table(vanilla, conditions, fits, negatives, positives, cfg) -> str:
    vanilla_success = success_rate(vanilla)
    final = fits["final_energy"]
    held_out = negatives["final_energy"]
    reference = float(np.mean(held_out))
    vanilla_fpr = BinaryRates.from_scores(held_out, [], final.conformal_threshold).fpr
    rows = [
        ["vanilla (held-out)", len(vanilla), percent(vanilla_success), "", "0", "0", "", percent(vanilla_fpr)]
    ]
    for condition, episodes in conditions.items():
        scores = positives[condition]["final_energy"]
        shift = float(np.mean(scores)) - reference
        drop = 100 * (vanilla_success - success_rate(episodes))
        sigma_units = f"{shift / final.sigma_v:+.2f}" if final.sigma_v > 0 else "n/a"
        rows.append(
            [
                condition,
                len(episodes),
                percent(success_rate(episodes)),
                f"{drop:+.1f} pts",
                f"{shift:+.4g}",
                sigma_units,
                auroc_interval(held_out, scores, cfg),
                percent(BinaryRates.from_scores(held_out, scores, final.conformal_threshold).tpr),
            ]
        )
    headers = [
        "Condition",
        "Episodes",
        "Success",
        "Success drop",
        "Score shift",
        "Shift / sigma_v",
        "AUROC [95% CI]",
        "Flagged at conformal T",
    ]
    return markdown_table(headers, rows)


def _auroc_table(conditions, names, negatives, positives, cfg) -> str:
    rows = [
        [
            condition,
            len(episodes),
            *(auroc_interval(negatives[n], positives[condition][n], cfg) for n in names),
        ]
        for condition, episodes in conditions.items()
    ]
    return markdown_table(["Condition", "Episodes", *names], rows)


def _figures(cfg, fits, calibration_scores, negatives, positives, names) -> None:
    def curve(negative, positive):
        fpr, tpr, _ = roc_curve(negative, positive)
        return fpr, tpr, auroc(negative, positive)

    final = "final_energy"
    plot_roc(
        {c: curve(negatives[final], p[final]) for c, p in positives.items()}, cfg.output_dir / "roc_curve.png"
    )
    plot_roc(
        {n: curve(negatives[n], positives[ALL_CONDITIONS][n]) for n in names},
        cfg.output_dir / "roc_baselines.png",
    )
    fit = fits[final]
    groups = {"calibration": calibration_scores, "vanilla (held-out)": negatives[final]}
    groups.update({c: p[final] for c, p in positives.items() if c != ALL_CONDITIONS})
    thresholds = {
        f"T = mu_v + {cfg.k:g} sigma_v": fit.with_k(cfg.k).threshold,
        f"T conformal (α={percent(cfg.false_alarm_rate)})": fit.conformal_threshold,
    }
    xlabel = f"rollout score ({cfg.aggregation} of chunk final energies)"
    plot_score_histograms(groups, thresholds, cfg.output_dir / "energy_histogram.png", xlabel)
