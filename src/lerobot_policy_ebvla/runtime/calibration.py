"""The OOD calibration that ships with a checkpoint, and the monitor that applies it (Sec. III-C, Eq. 5).

The anomaly score of a chunk is its final energy E(a^(K_inf), C). A rollout's score aggregates its chunks'
final energies (`rollout_score`, mean by default). From the scores of vanilla (in-distribution) rollouts we
take their mean mu_v and standard deviation sigma_v and flag a rollout as OOD when

    E > T = mu_v + k * sigma_v                                                             (Eq. 5)

or, with `rule="conformal"`, when E exceeds the conformal threshold of a stated false-alarm rate alpha
(`threshold.py` holds both rules and the decision itself).

`OODCalibration` holds the statistics and lives next to a checkpoint as `ood_calibration.json`;
`EnergyOODMonitor` applies it at run time. Evaluating a calibration (Table III) is analysis and lives in
`monitoring/ood.py`.

The final energy's level follows the task's phase (the energy of a normal chunk late in an episode is not the
energy of a normal first chunk), so a calibration may instead score each chunk against the vanilla energy at
the same chunk index: the *phase energy* z_t = (E_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`). Its per-index
statistics are saved in the calibration (`score="phase_energy"`), and `OODCalibration.chunk_score` turns a
chunk's (final energy, chunk index) into the score the threshold applies to.

A calibration may also score what the policy sees rather than its energy: the *context distance*
(`score="context_distance"`, opt-in) is the Mahalanobis distance of the chunk's pooled last-block context
c = mean over tokens of C_L (`EBVLAPolicy.context_features`) from the vanilla calibration contexts,

    d(c) = sqrt((c - mu_c)^T P (c - mu_c)),    P the inverse of the Ledoit-Wolf shrunk covariance,

`ContextStatistics`, fitted on every chunk of the calibration rollouts; mu_v and sigma_v are then those of the
vanilla rollout scores, as for the energy. mu_c and P (D and D x D numbers, D = 896 for the VLM) are saved
beside the JSON in `ood_calibration_context.safetensors`.

The two see different failures (the energy how well the action chain converged, the context distance what the
policy sees), so a calibration may watch both: the *energy and context* score (`score="energy_and_context"`,
opt-in) standardizes a rollout's final energy E and context distance d, each by the mean and std of the vanilla
calibration rollouts' scores (`CombinedStatistics`), and takes the larger,

    s = max((E - mu_E) / sigma_E, (d - mu_d) / sigma_d),

which is then calibrated like the energy (mu_v, sigma_v of the vanilla rollouts' s; T = mu_v + k sigma_v). E and
d are each aggregated over the rollout's chunks first (`OODCalibration.score_rollout`); a single chunk's score
is the same formula on that chunk alone (`OODCalibration.chunk_score`).

The Mahalanobis distance assumes the vanilla contexts form one Gaussian cloud; the *context k-NN distance*
(`score="context_knn"`, opt-in) assumes nothing: the Euclidean distance of the chunk's pooled context,
standardized per dimension by the vanilla mean and std, to its k-th nearest standardized vanilla context,

    d_k(c) = || z(c) - z(c_(k)) ||,    z(c) = (c - mean) / std,    c_(k) the k-th nearest calibration context,

`ContextNeighbours`, the report's `knn` baseline for a held-out chunk. mu_v and sigma_v are those of the vanilla
rollout scores, each calibration rollout scored without its own chunks (leave-one-episode-out), as the report
does. It keeps every calibration context, N x D float32 numbers (D = 128 for the light policy: a few MB for a
few thousand chunks), with their mean, std and k, beside the JSON in `ood_calibration_neighbours.safetensors`.
"""

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import safetensors.numpy
import torch
from safetensors import SafetensorError
from torch import Tensor

from .threshold import ArrayLike, MeanStd, as_array, conformal_threshold, exceeds, mean_std_threshold

OOD_CALIBRATION_FILENAME = "ood_calibration.json"
# The context distance's mean and precision, beside the JSON: D x D numbers are no JSON (D = 896 for the VLM).
OOD_CONTEXT_FILENAME = "ood_calibration_context.safetensors"
# The JSON field that names that file, with its D and SHA-256 (`OODCalibration.save`).
CONTEXT_FIELD = "context_statistics"
# The context k-NN distance's calibration features (N x D), beside the JSON, and the JSON field naming them.
OOD_NEIGHBOURS_FILENAME = "ood_calibration_neighbours.safetensors"
NEIGHBOURS_FIELD = "context_neighbours"
SCORE_AGGREGATIONS = ("mean", "max", "last", "median")
THRESHOLD_RULES = ("mean_std", "conformal")
# The chunk scores a run-time calibration can compute from what the policy reports: the final energy, the
# final energy against the vanilla energy at the same chunk index, the distance of the chunk's pooled context
# from the vanilla contexts, the larger of the first and the third, each standardized, and the distance of the
# chunk's pooled context to its k-th nearest vanilla context.
CALIBRATED_SCORES = ("final_energy", "phase_energy", "context_distance", "energy_and_context", "context_knn")
# Which nearest vanilla context the context k-NN distance measures to, unless told. The nearest: vanilla
# rollouts differ mostly by where the scene's objects start, so a vanilla chunk has a close twin among the
# calibration chunks while a shifted one does not; from the 5th the spread of starting scenes drowns a small
# shift (a distractor: AUROC 0.65 / 0.74 on the first 3 chunks at k = 5, 0.98 / 1.00 at k = 1; BENCHMARKS.md,
# section 6).
DEFAULT_KNN_K = 1
# The scores a calibration computes from each chunk's pooled context.
CONTEXT_SCORES = ("context_distance", "energy_and_context", "context_knn")
# Of those, the ones computed with `ContextStatistics` (the others with `ContextNeighbours`).
STATISTICS_SCORES = ("context_distance", "energy_and_context")
# sigma_v[t] is at least this fraction of the pooled sigma of all vanilla chunk energies.
PHASE_SIGMA_FLOOR = 0.1
# And at least this, so that a calibration of identical energies still divides by a positive number.
_MIN_SIGMA = 1e-12


def rollout_score(chunk_energies: ArrayLike, aggregation: str = "mean") -> float:
    """Forms a rollout's anomaly score from the final energies (or other scores) of its chunks, in order.

    Args:
        chunk_energies: E(a^(K_inf), C) of each predicted chunk of the rollout.
        aggregation: "mean" (default, every chunk counts equally), "max" (the least confident chunk),
            "last" (the most recent chunk, what a streaming monitor sees) or "median" (robust to a few
            outlying chunks). With "mean" and "max" one +inf chunk makes the score +inf.

    Raises:
        ValueError: No energies, or an unknown aggregation.
    """
    if aggregation not in SCORE_AGGREGATIONS:
        raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {aggregation!r}.")
    energies = as_array(chunk_energies)
    if energies.size == 0:
        raise ValueError("A rollout score needs at least one chunk energy.")
    reduce = {"mean": np.mean, "max": np.max, "last": lambda e: e[-1], "median": np.median}[aggregation]
    return float(reduce(energies))


def _ndim(values: ArrayLike | float) -> int:
    return values.ndim if isinstance(values, Tensor) else np.ndim(values)


def _to_json_number(value: float | None) -> float | str | None:
    return "inf" if value == math.inf else value


@dataclass(frozen=True)
class PhaseStatistics:
    """mu_v[t] and sigma_v[t]: the vanilla final energy at each chunk index t, the phase energy's reference.

    The phase energy of a chunk is z_t = (E_t - mu_v[t]) / sigma_v[t]: how far its final energy lies above
    what vanilla rollouts have at the same point of the task. Fit with `fit` on vanilla episodes.

    - mu_v[t] and sigma_v[t] (population std) are over the vanilla episodes that reached index t, finite
      energies only; an index where none has a finite energy takes the previous index's statistics (index 0
      the pooled ones).
    - sigma_v[t] is floored at `PHASE_SIGMA_FLOOR` (0.1) times the pooled sigma, the std of every vanilla
      chunk energy of every index together: a late index reached by one or two episodes would otherwise
      divide by almost nothing.
    - Indices past the longest vanilla episode use the last index's statistics.

    Args:
        mean: mu_v[t] for t = 0 .. T-1.
        std: sigma_v[t], already floored (every entry > 0).
    """

    mean: tuple[float, ...]
    std: tuple[float, ...]

    def __post_init__(self):
        object.__setattr__(self, "mean", tuple(float(m) for m in self.mean))
        object.__setattr__(self, "std", tuple(float(s) for s in self.std))
        if not self.mean or len(self.mean) != len(self.std):
            raise ValueError(
                f"`mean` and `std` need one entry per chunk index, got {len(self.mean)} and {len(self.std)}."
            )
        values = np.array([*self.mean, *self.std])
        if not np.all(np.isfinite(values)) or min(self.std) <= 0:
            raise ValueError("Phase statistics must be finite, with every std > 0.")

    @classmethod
    def fit(cls, episode_energies: Sequence[ArrayLike]) -> "PhaseStatistics":
        """Fits on the final energies of vanilla episodes, each in chunk order (index t is entry t).

        Raises:
            ValueError: No finite energy at all.
        """
        series = [as_array(e) for e in episode_energies]
        pooled = np.concatenate(series) if series else np.zeros(0)
        pooled = pooled[np.isfinite(pooled)]
        if pooled.size == 0:
            raise ValueError("Cannot fit phase statistics without a finite vanilla final energy.")
        floor = max(PHASE_SIGMA_FLOOR * float(pooled.std()), _MIN_SIGMA)
        previous = (float(pooled.mean()), max(float(pooled.std()), floor))
        means, stds = [], []
        for t in range(max(len(s) for s in series)):
            at_t = np.array([s[t] for s in series if len(s) > t])
            at_t = at_t[np.isfinite(at_t)]
            if at_t.size:
                previous = (float(at_t.mean()), max(float(at_t.std()), floor))
            means.append(previous[0])
            stds.append(previous[1])
        return cls(tuple(means), tuple(stds))

    def z(self, final_energy: ArrayLike | float, chunk_index: ArrayLike | int) -> np.ndarray:
        """The phase energy (E_t - mu_v[t]) / sigma_v[t] of each (final energy, chunk index) pair."""
        index = np.atleast_1d(np.asarray(chunk_index))
        if index.size and (not np.issubdtype(index.dtype, np.integer) or index.min() < 0):
            raise ValueError(f"`chunk_index` must be integers >= 0, got {chunk_index!r}.")
        index = np.minimum(index, len(self.mean) - 1)
        return (as_array(final_energy) - np.asarray(self.mean)[index]) / np.asarray(self.std)[index]


def ledoit_wolf_covariance(centered: np.ndarray) -> np.ndarray:
    """Ledoit-Wolf (2004) shrinkage of the covariance of (N, D) centered samples toward mu * I.

    D can exceed N (896 features from a few hundred chunks): the sample covariance is then singular, the
    shrunk one is not.
    """
    n, d = centered.shape
    sample_cov = centered.T @ centered / n
    mu = np.trace(sample_cov) / d
    # The sum of the entries' variances. The sum of all entries of squared.T @ squared, with squared = centered**2,
    # is the sum over samples of |x|^4: O(N D) instead of O(N D^2).
    beta = (np.sum(np.sum(centered**2, axis=1) ** 2) / n - np.sum(sample_cov**2)) / n
    delta = np.sum((sample_cov - mu * np.eye(d)) ** 2)  # distance of S to the target
    shrinkage = 0.0 if delta == 0 else min(beta, delta) / delta
    return (1 - shrinkage) * sample_cov + shrinkage * mu * np.eye(d)


@dataclass(frozen=True, eq=False)
class ContextStatistics:
    """mu_c and P: the mean and precision of vanilla context features, the context distance's reference.

    The context distance of a chunk is the Mahalanobis distance d(c) = sqrt((c - mu_c)^T P (c - mu_c)) of its
    pooled context c (`EBVLAPolicy.context_features`, the mean over tokens of the last block's context C_L)
    from the contexts of vanilla rollouts. P inverts their Ledoit-Wolf shrunk covariance
    (`ledoit_wolf_covariance`); `fit` on every chunk of the calibration rollouts.

    Args:
        mean: mu_c, (D,).
        precision: P, (D, D), symmetric.
        n_chunks: How many vanilla chunks the statistics come from.
    """

    mean: np.ndarray
    precision: np.ndarray
    n_chunks: int

    def __post_init__(self):
        mean = np.asarray(self.mean, dtype=np.float64)
        precision = np.asarray(self.precision, dtype=np.float64)
        if mean.ndim != 1 or mean.size == 0 or precision.shape != (mean.size, mean.size):
            raise ValueError(
                f"Context statistics need `mean` (D,) and `precision` (D, D); got {mean.shape} and "
                f"{precision.shape}."
            )
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(precision))):
            raise ValueError("Context statistics `mean` and `precision` must be finite.")
        if self.n_chunks < 2:
            raise ValueError(f"Context statistics need `n_chunks` >= 2, got {self.n_chunks}.")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "precision", precision)
        object.__setattr__(self, "n_chunks", int(self.n_chunks))

    @classmethod
    def fit(cls, features: ArrayLike) -> "ContextStatistics":
        """Fits on (N >= 2, D) vanilla context features, one row per chunk.

        Raises:
            ValueError: Not (N >= 2, D), or a non-finite feature.
        """
        features = _features_to_fit(features, "context statistics")
        mean = features.mean(axis=0)
        covariance = ledoit_wolf_covariance(features - mean)
        try:
            # The shrunk covariance is positive definite unless the shrinkage is 0: invert it through its Cholesky
            # factor, several times faster than the pseudo-inverse (a refit per calibration episode adds up).
            inverse_factor = np.linalg.inv(np.linalg.cholesky(covariance))
            precision = inverse_factor.T @ inverse_factor
        except np.linalg.LinAlgError:
            precision = np.linalg.pinv(covariance, hermitian=True)
        return cls(mean, precision, features.shape[0])

    @property
    def dim(self) -> int:
        """D, the size of the context features."""
        return self.mean.size

    def distance(self, features: ArrayLike) -> np.ndarray:
        """d(c) of each context feature: (N,) for (N, D) features, (1,) for one (D,) feature.

        Raises:
            ValueError: The features are not D-dimensional (a calibration of another backbone).
        """
        centered = _context_features(features, self.dim, "context_distance") - self.mean
        return np.sqrt(np.maximum(np.sum((centered @ self.precision) * centered, axis=1), 0.0))

    def to_bytes(self) -> bytes:
        """The safetensors file of `OOD_CONTEXT_FILENAME`: mu_c and P in float64."""
        n_chunks = np.array(self.n_chunks, dtype=np.int64)
        return safetensors.numpy.save({"mean": self.mean, "precision": self.precision, "n_chunks": n_chunks})

    @classmethod
    def from_bytes(cls, data: bytes) -> "ContextStatistics":
        """Reads what `to_bytes` wrote.

        Raises:
            ValueError: Not a safetensors file holding `mean`, `precision` and `n_chunks`, or invalid statistics.
        """
        tensors = _read_tensors(data, ("mean", "precision", "n_chunks"))
        return cls(tensors["mean"], tensors["precision"], int(tensors["n_chunks"]))


def kth_nearest_distance(
    queries: np.ndarray, reference: np.ndarray, k: int, excluded: np.ndarray | None = None
) -> np.ndarray:
    """Euclidean distance of each (N, D) query to its k-th nearest row of the (M, D) reference.

    `excluded`, (M,) bool, leaves reference rows out (a calibration episode's own chunks). With fewer than k rows
    left, the farthest one counts; with none, the distance is +inf. The report's `knn` baseline and the run-time
    `ContextNeighbours` both compute it here, so they give the same number.
    """
    squared = (queries**2).sum(axis=1)[:, None] - 2 * queries @ reference.T
    distances = np.sqrt(np.maximum(squared + (reference**2).sum(axis=1)[None, :], 0.0))
    n_left = reference.shape[0]
    if excluded is not None:
        distances[:, excluded] = np.inf
        n_left -= int(np.sum(excluded))
    k = min(k, n_left)
    if k == 0:
        return np.full(len(queries), np.inf)
    return np.partition(distances, k - 1, axis=1)[:, k - 1]


@dataclass(frozen=True, eq=False)
class ContextNeighbours:
    """The vanilla context features themselves, the context k-NN distance's reference.

    The context k-NN distance of a chunk is the Euclidean distance of its pooled context c
    (`EBVLAPolicy.context_features`), standardized per dimension as z = (c - mean) / std, to its k-th nearest
    standardized vanilla context: the report's `knn` baseline for a held-out chunk. Unlike the Mahalanobis
    distance it assumes no Gaussian shape, so a context between two vanilla modes is still far from both.
    `fit` on every chunk of the calibration rollouts.

    It keeps every calibration feature, N x D float32 numbers: for the light policy (D = 128) a few thousand
    chunks are a few MB (4,000 chunks: 2 MB), for the VLM (D = 896) about 7 times more.

    Args:
        features: The vanilla pooled contexts, (N, D), stored as float32.
        mean: Their per-dimension mean, (D,).
        std: Their per-dimension population std, (D,), floored at 1e-12 (a constant dimension carries no
            distance).
        k: Which nearest neighbour's distance is the score (`ebvla-ood-report --knn_k`); with fewer than k
            features, the farthest.
    """

    features: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    k: int

    def __post_init__(self):
        features = np.asarray(self.features, dtype=np.float32)
        mean = np.asarray(self.mean, dtype=np.float64)
        std = np.asarray(self.std, dtype=np.float64)
        if features.ndim != 2 or features.shape[0] < 1 or features.shape[1] == 0:
            raise ValueError(f"Context neighbours need `features` (N >= 1, D), got shape {features.shape}.")
        d = features.shape[1]
        if mean.shape != (d,) or std.shape != (d,):
            raise ValueError(
                f"Context neighbours need `mean` and `std` of shape ({d},), one per feature dimension; got "
                f"{mean.shape} and {std.shape}."
            )
        if not (np.all(np.isfinite(features)) and np.all(np.isfinite(mean)) and np.all(np.isfinite(std))):
            raise ValueError("Context neighbours `features`, `mean` and `std` must be finite.")
        if np.any(std <= 0):
            raise ValueError("Context neighbours `std` must be > 0 in every dimension.")
        if int(self.k) != self.k or self.k < 1:
            raise ValueError(f"Context neighbours need `k` (nearest neighbours) >= 1, got {self.k}.")
        object.__setattr__(self, "features", features)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "std", std)
        object.__setattr__(self, "k", int(self.k))
        # The standardized reference, computed once: every chunk is compared with all of it.
        object.__setattr__(self, "_reference", (features.astype(np.float64) - mean) / std)

    @classmethod
    def fit(cls, features: ArrayLike, k: int = DEFAULT_KNN_K) -> "ContextNeighbours":
        """Keeps (N >= 2, D) vanilla context features, one row per chunk, with their mean and std.

        Raises:
            ValueError: Not (N >= 2, D), or a non-finite feature.
        """
        features = _features_to_fit(features, "context neighbours")
        return cls(features, features.mean(axis=0), np.maximum(features.std(axis=0), _MIN_SIGMA), k)

    @property
    def dim(self) -> int:
        """D, the size of the context features."""
        return self.mean.size

    @property
    def n_chunks(self) -> int:
        """N, how many vanilla chunks the features come from."""
        return self.features.shape[0]

    def distance(self, features: ArrayLike, excluded: np.ndarray | None = None) -> np.ndarray:
        """The k-NN distance of each context feature: (N,) for (N, D) features, (1,) for one (D,) feature.

        `excluded`, (n_chunks,) bool, leaves calibration features out (the report's leave-one-episode-out
        scores of the calibration rollouts); a run-time chunk is compared with all of them.

        Raises:
            ValueError: The features are not D-dimensional (a calibration of another backbone).
        """
        queries = (_context_features(features, self.dim, "context_knn") - self.mean) / self.std
        return kth_nearest_distance(queries, self._reference, self.k, excluded)

    def to_bytes(self) -> bytes:
        """The safetensors file of `OOD_NEIGHBOURS_FILENAME`: the features in float32, mean and std in float64."""
        return safetensors.numpy.save(
            {
                "features": self.features,
                "mean": self.mean,
                "std": self.std,
                "k": np.array(self.k, dtype=np.int64),
            }
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> "ContextNeighbours":
        """Reads what `to_bytes` wrote.

        Raises:
            ValueError: Not a safetensors file holding `features`, `mean`, `std` and `k`, or invalid ones.
        """
        tensors = _read_tensors(data, ("features", "mean", "std", "k"))
        return cls(tensors["features"], tensors["mean"], tensors["std"], int(tensors["k"]))


@dataclass(frozen=True)
class CombinedStatistics:
    """(mu_v, sigma_v) of the final energy's and of the context distance's vanilla rollout scores, in that order.

    They standardize the two scores that `score="energy_and_context"` combines: a rollout with final energy E
    and context distance d (each aggregated over its chunks) scores max(z_E, z_d), z_E = (E - mu_E) / sigma_E
    and z_d = (d - mu_d) / sigma_d. In units of its own vanilla spread neither score dominates by its scale, and
    the max is high when either is: a failure one score misses the other can still flag. Fit with `fit` on the
    calibration rollouts' scores.

    Args:
        mean: (mu_E, mu_d).
        std: (sigma_E, sigma_d), population stds, each > 0.
    """

    mean: tuple[float, float]
    std: tuple[float, float]

    def __post_init__(self):
        object.__setattr__(self, "mean", tuple(float(m) for m in self.mean))
        object.__setattr__(self, "std", tuple(float(s) for s in self.std))
        if len(self.mean) != 2 or len(self.std) != 2:
            raise ValueError(
                "Combined statistics need `mean` and `std` with one entry per score (final energy, context "
                f"distance); got {len(self.mean)} and {len(self.std)}."
            )
        if not np.all(np.isfinite([*self.mean, *self.std])) or min(self.std) <= 0:
            raise ValueError(
                f"Combined statistics must be finite, with every std > 0; got mean {self.mean}, std {self.std}."
            )

    @classmethod
    def fit(cls, energy_scores: ArrayLike, context_scores: ArrayLike) -> "CombinedStatistics":
        """Fits on the vanilla calibration rollouts' final-energy and context-distance scores.

        Non-finite scores are left out with a warning, as in `OODCalibration.fit`; a std of 0 (identical
        scores) is raised to 1e-12, so that a calibration of identical scores still divides by a positive
        number.

        Raises:
            ValueError: No finite score of one of the two.
        """
        energy = MeanStd.fit(energy_scores, "vanilla final-energy")
        context = MeanStd.fit(context_scores, "vanilla context-distance")
        return cls((energy.mean, context.mean), (max(energy.std, _MIN_SIGMA), max(context.std, _MIN_SIGMA)))

    def z(self, energy: ArrayLike | float, context_distance: ArrayLike | float) -> np.ndarray:
        """(N, 2): z_E and z_d of each (final energy, context distance) pair."""
        energy, context_distance = as_array(energy), as_array(context_distance)
        if energy.shape != context_distance.shape:
            raise ValueError(
                f"Give one context distance per final energy; got {energy.size} energies and "
                f"{context_distance.size} distances."
            )
        return (np.stack([energy, context_distance], axis=1) - np.asarray(self.mean)) / np.asarray(self.std)

    def combine(self, energy: ArrayLike | float, context_distance: ArrayLike | float) -> np.ndarray:
        """(N,): max(z_E, z_d) of each (final energy, context distance) pair. NaN in either gives NaN."""
        z = self.z(energy, context_distance)
        # np.max propagates NaN, so the rule `score <= T` flags it, as it flags a NaN energy.
        return np.max(z, axis=1)


def _features_to_fit(features: ArrayLike, what: str) -> np.ndarray:
    """(N >= 2, D) finite vanilla context features as float64; a ValueError otherwise."""
    features = _float64(features)
    if features.ndim != 2 or features.shape[0] < 2:
        raise ValueError(f"Context features to fit must be (N >= 2, D), got shape {features.shape}.")
    if not np.all(np.isfinite(features)):
        raise ValueError(f"Cannot fit {what} on non-finite context features.")
    return features


def _context_features(features: ArrayLike, dim: int, score: str) -> np.ndarray:
    """(N, D) float64 pooled contexts from (N, D) or one (D,); raises a ValueError naming the expected D."""
    features = _float64(features)
    if features.ndim not in (1, 2) or features.shape[-1] != dim:
        raise ValueError(
            f"`context_features` must be (N, {dim}): the calibration's {score} was fitted on {dim}-dimensional "
            f"pooled contexts; got shape {features.shape}. Calibrate this checkpoint again "
            f"(`ebvla-ood-report --score={score}`)."
        )
    return np.atleast_2d(features)


def _read_tensors(data: bytes, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file that must hold exactly `names`; a ValueError says what it holds."""
    try:
        tensors = safetensors.numpy.load(data)
    except SafetensorError as e:
        raise ValueError(f"not a safetensors file ({e})") from e
    if set(tensors) != set(names):
        raise ValueError(f"expected the tensors {', '.join(f'`{n}`' for n in names)}, got {sorted(tensors)}")
    return tensors


def _float64(values: ArrayLike) -> np.ndarray:
    """Any array or tensor as a float64 array of the same shape (tensors detached, on the CPU)."""
    if isinstance(values, Tensor):
        values = values.detach().to("cpu", torch.float64).numpy()
    return np.asarray(values, dtype=np.float64)


@dataclass(frozen=True)
class OODCalibration:
    """Vanilla-rollout statistics that define the OOD threshold T (Eq. 5, or the conformal quantile).

    Args:
        mu_v: Mean rollout score of the vanilla (in-distribution) rollouts.
        sigma_v: Population standard deviation of the vanilla rollout scores.
        k: Sensitivity multiplier of Eq. 5; lower catches more OOD rollouts at the cost of more false alarms.
        aggregation: How a rollout's chunk energies were reduced to its score (see `rollout_score`). The
            monitor must aggregate the same way for T to mean anything.
        n_rollouts: Number of vanilla rollouts the statistics come from.
        false_alarm_rate: alpha of `conformal_threshold`, None when not computed.
        conformal_threshold: The (1 - alpha) conformal quantile of the vanilla scores (+inf when there were
            too few rollouts for alpha), None when not computed.
        rule: Which threshold the monitor applies: "mean_std" (Eq. 5, the paper's, default) or "conformal".
        score: The chunk score the statistics are of: "final_energy" (the paper's, default),
            "phase_energy" (the final energy against the vanilla energy at the same chunk index),
            "context_distance" (the Mahalanobis distance of the chunk's pooled context from the vanilla
            contexts), "energy_and_context" (the larger of the two standardized, `CombinedStatistics`) or
            "context_knn" (the distance of the chunk's standardized pooled context to its k-th nearest vanilla
            one, `ContextNeighbours`).
        phase_mean: mu_v[t] of `PhaseStatistics`, for `score="phase_energy"`; None otherwise.
        phase_std: sigma_v[t] of `PhaseStatistics`, for `score="phase_energy"`; None otherwise.
        context: mu_c and P of `ContextStatistics`, for `score="context_distance"` and
            `score="energy_and_context"`; None otherwise. Saved beside the JSON in `OOD_CONTEXT_FILENAME`, not
            compared by `==`.
        combined_mean: (mu_E, mu_d) of `CombinedStatistics`, for `score="energy_and_context"`; None otherwise.
        combined_std: (sigma_E, sigma_d) of `CombinedStatistics`, for `score="energy_and_context"`; None
            otherwise.
        neighbours: The vanilla context features of `ContextNeighbours`, for `score="context_knn"`; None
            otherwise. Saved beside the JSON in `OOD_NEIGHBOURS_FILENAME`, not compared by `==`.
    """

    mu_v: float
    sigma_v: float
    k: float = 1.0
    aggregation: str = "mean"
    n_rollouts: int = 0
    false_alarm_rate: float | None = None
    conformal_threshold: float | None = None
    rule: str = "mean_std"
    score: str = "final_energy"
    phase_mean: tuple[float, ...] | None = None
    phase_std: tuple[float, ...] | None = None
    context: ContextStatistics | None = field(default=None, compare=False)
    combined_mean: tuple[float, float] | None = None
    combined_std: tuple[float, float] | None = None
    neighbours: ContextNeighbours | None = field(default=None, compare=False)

    def __post_init__(self):
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        if not (math.isfinite(self.mu_v) and math.isfinite(self.sigma_v) and self.sigma_v >= 0):
            raise ValueError(
                f"`mu_v` and `sigma_v` must be finite, sigma_v >= 0; got {self.mu_v}, {self.sigma_v}."
            )
        if self.rule not in THRESHOLD_RULES:
            raise ValueError(f"`rule` must be one of {THRESHOLD_RULES}, got {self.rule!r}.")
        if self.rule == "conformal" and self.conformal_threshold is None:
            raise ValueError(
                "`rule='conformal'` needs a `conformal_threshold` (fit with `false_alarm_rate`)."
            )
        if self.score not in CALIBRATED_SCORES:
            raise ValueError(f"`score` must be one of {CALIBRATED_SCORES}, got {self.score!r}.")
        if (self.phase_mean is None) != (self.phase_std is None):
            raise ValueError("`phase_mean` and `phase_std` come together: give both or neither.")
        if self.phase_mean is not None:
            # Validates them, and stores tuples whether they came from a fit or from a JSON list.
            phase = PhaseStatistics(self.phase_mean, self.phase_std)
            object.__setattr__(self, "phase_mean", phase.mean)
            object.__setattr__(self, "phase_std", phase.std)
        elif self.score == "phase_energy":
            raise ValueError("`score='phase_energy'` needs `phase_mean` and `phase_std` (`PhaseStatistics`).")
        if self.context is not None and not isinstance(self.context, ContextStatistics):
            raise ValueError(f"`context` must be `ContextStatistics`, got {type(self.context).__name__}.")
        if self.score in STATISTICS_SCORES and self.context is None:
            raise ValueError(f"`score={self.score!r}` needs `context` (`ContextStatistics`).")
        if self.neighbours is not None and not isinstance(self.neighbours, ContextNeighbours):
            raise ValueError(
                f"`neighbours` must be `ContextNeighbours`, got {type(self.neighbours).__name__}."
            )
        if self.score == "context_knn" and self.neighbours is None:
            raise ValueError("`score='context_knn'` needs `neighbours` (`ContextNeighbours`).")
        if (self.combined_mean is None) != (self.combined_std is None):
            raise ValueError("`combined_mean` and `combined_std` come together: give both or neither.")
        if self.combined_mean is not None:
            combined = CombinedStatistics(self.combined_mean, self.combined_std)
            object.__setattr__(self, "combined_mean", combined.mean)
            object.__setattr__(self, "combined_std", combined.std)
        elif self.score == "energy_and_context":
            raise ValueError(
                "`score='energy_and_context'` needs `combined_mean` and `combined_std` (`CombinedStatistics`)."
            )

    @classmethod
    def fit(
        cls,
        vanilla_scores: ArrayLike,
        k: float = 1.0,
        aggregation: str = "mean",
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
        score: str = "final_energy",
        phase: PhaseStatistics | None = None,
        context: ContextStatistics | None = None,
        combined: CombinedStatistics | None = None,
        neighbours: ContextNeighbours | None = None,
    ) -> "OODCalibration":
        """Estimates mu_v and sigma_v, and with `false_alarm_rate` the conformal threshold, from vanilla scores.

        Non-finite scores (a vanilla rollout whose refinement diverged) are left out with a warning: one
        +inf would make mu_v infinite and the detector useless.

        Args:
            vanilla_scores: The vanilla rollouts' scores, each aggregated from its chunks' `score`.
            score: The chunk score `vanilla_scores` were aggregated from (`CALIBRATED_SCORES`).
            phase: The per-index statistics the phase energy was computed with, for `score="phase_energy"`.
            context: The context statistics the context distance was computed with, for
                `score="context_distance"` and `score="energy_and_context"`.
            combined: The statistics the final energy and the context distance were standardized with, for
                `score="energy_and_context"`.
            neighbours: The vanilla context features the k-NN distance was computed with, for
                `score="context_knn"`.

        Raises:
            ValueError: No finite score to fit on.
        """
        stats = MeanStd.fit(vanilla_scores, "vanilla")
        conformal = None
        if false_alarm_rate is not None:
            conformal = conformal_threshold(vanilla_scores, false_alarm_rate, "vanilla")
        phase_mean, phase_std = (None, None) if phase is None else (phase.mean, phase.std)
        combined_mean, combined_std = (None, None) if combined is None else (combined.mean, combined.std)
        return cls(
            stats.mean,
            stats.std,
            float(k),
            aggregation,
            stats.n,
            false_alarm_rate,
            conformal,
            rule,
            score,
            phase_mean,
            phase_std,
            context,
            combined_mean,
            combined_std,
            neighbours,
        )

    @property
    def phase(self) -> PhaseStatistics | None:
        """The per-index statistics of the phase energy, None when the calibration has none."""
        return None if self.phase_mean is None else PhaseStatistics(self.phase_mean, self.phase_std)

    @property
    def combined(self) -> CombinedStatistics | None:
        """The standardization of the energy-and-context score, None when the calibration has none."""
        return (
            None if self.combined_mean is None else CombinedStatistics(self.combined_mean, self.combined_std)
        )

    @property
    def needs_context_features(self) -> bool:
        """Whether `chunk_score` needs each chunk's pooled context (`EBVLAPolicy.context_features`)."""
        return self.score in CONTEXT_SCORES

    def chunk_score(
        self,
        final_energy: ArrayLike | float,
        chunk_index: ArrayLike | int | None = None,
        context_features: ArrayLike | None = None,
    ) -> float | np.ndarray:
        """The calibrated score of a chunk: what `threshold` and `rollout_score` apply to.

        For `score="final_energy"` it is the final energy itself; for `score="phase_energy"` it is
        (E - mu_v[t]) / sigma_v[t] at the chunk's 0-based index t in its episode; for `score="context_distance"`
        it is the Mahalanobis distance d(c) of the chunk's pooled context (`ContextStatistics`); for
        `score="energy_and_context"` it is max(z_E, z_d) of the chunk's E and d(c) (`CombinedStatistics`), the
        score of a rollout of that one chunk; for `score="context_knn"` it is the distance of the chunk's
        standardized pooled context to its k-th nearest vanilla one (`ContextNeighbours`).

        Args:
            final_energy: One final energy, or one per environment ((B,) array or tensor).
            chunk_index: The chunk's index in its episode: an int, or one per environment. Needed by the
                phase energy only.
            context_features: The chunk's pooled context, (D,), or one per environment, (B, D). Needed by
                the context scores (`CONTEXT_SCORES`) only.

        Returns:
            A float for a scalar energy, else an array with one score per entry.

        Raises:
            ValueError: The score's input (`chunk_index`, `context_features`) is missing, or the context
                features are not one D-dimensional row per final energy.
        """
        scalar = _ndim(final_energy) == 0
        if self.score in ("context_distance", "context_knn"):
            return self._context_distance(final_energy, context_features)
        if self.score == "energy_and_context":
            distances = self._context_distance(final_energy, context_features)
            scores = self.combined.combine(final_energy, distances)
            return float(scores[0]) if _ndim(context_features) == 1 else scores
        if self.score == "final_energy":
            scores = as_array(final_energy)
        elif chunk_index is None:
            raise ValueError("The phase energy needs the chunk's index in its episode (`chunk_index`).")
        else:
            scores = self.phase.z(final_energy, chunk_index)
        return float(scores[0]) if scalar and np.ndim(chunk_index) == 0 else scores

    def _context_distance(
        self, final_energy: ArrayLike | float, context_features: ArrayLike | None
    ) -> float | np.ndarray:
        if context_features is None:
            raise ValueError(
                f"The {self.score} score needs each chunk's pooled context (`context_features`, (B, D), from "
                "`EBVLAPolicy.context_features`)."
            )
        reference = self.neighbours if self.score == "context_knn" else self.context
        scores = reference.distance(context_features)
        n_energies = as_array(final_energy).size
        if scores.size != n_energies:
            raise ValueError(
                f"`context_features` has {scores.size} row(s) and `final_energy` {n_energies} entries: give one "
                "pooled context per chunk."
            )
        return float(scores[0]) if _ndim(context_features) == 1 else scores

    def chunk_components(
        self,
        final_energy: ArrayLike | float,
        chunk_index: ArrayLike | int | None = None,
        context_features: ArrayLike | None = None,
    ) -> np.ndarray:
        """What a rollout's score is aggregated from, one row per chunk: (B, 1), the chunk score, or for
        `score="energy_and_context"` (B, 2), the chunk's final energy and context distance, which are each
        aggregated over the rollout before they are combined (`score_rollout`).

        Arguments and errors as in `chunk_score`.
        """
        if self.score != "energy_and_context":
            return as_array(self.chunk_score(final_energy, chunk_index, context_features))[:, None]
        distances = as_array(self._context_distance(final_energy, context_features))
        return np.stack([as_array(final_energy), distances], axis=1)

    def score_rollout(self, components: ArrayLike) -> float:
        """The rollout score the threshold applies to, from its chunks' `chunk_components` in chunk order.

        Each column is aggregated over the chunks (`rollout_score`, the calibration's aggregation); a
        single-column score is that aggregate, the energy-and-context score max(z_E, z_d) of the two aggregates.

        Raises:
            ValueError: `components` is not (N >= 1, n) with the calibration's n columns.
        """
        components = _float64(components)
        n = 2 if self.score == "energy_and_context" else 1
        if components.ndim != 2 or components.shape[1] != n:
            raise ValueError(
                f"`components` of a {self.score} rollout must be (N, {n}), one row of "
                f"`chunk_components` per chunk; got shape {components.shape}."
            )
        aggregates = [rollout_score(column, self.aggregation) for column in components.T]
        if self.score != "energy_and_context":
            return aggregates[0]
        return float(self.combined.combine(*aggregates)[0])

    @property
    def threshold(self) -> float:
        """The threshold of `rule`: mu_v + k * sigma_v, or the conformal quantile."""
        if self.rule == "conformal":
            return self.conformal_threshold
        return mean_std_threshold(self.mu_v, self.sigma_v, self.k)

    def with_k(self, k: float) -> "OODCalibration":
        """The same statistics with Eq. 5's threshold at another k (an explicit k selects Eq. 5)."""
        return dataclasses.replace(self, k=float(k), rule="mean_std")

    def save(self, checkpoint_dir: str | Path, overwrite: bool = False) -> Path:
        """Writes `ood_calibration.json` into a policy checkpoint folder (the `pretrained_model` folder).

        With context statistics, they go beside it into `OOD_CONTEXT_FILENAME`, and the JSON's
        `context_statistics` names that file with its D and its SHA-256, so that a file of another
        calibration is refused on loading. Context neighbours go the same way into `OOD_NEIGHBOURS_FILENAME`,
        named by the JSON's `context_neighbours` with their D, N, k and SHA-256.

        Raises:
            FileNotFoundError: The folder does not exist.
            ValueError: The folder is a training checkpoint that holds a `pretrained_model` folder.
            FileExistsError: A calibration exists and `overwrite` is False.
        """
        checkpoint_dir = Path(checkpoint_dir)
        if not checkpoint_dir.is_dir():
            raise FileNotFoundError(f"Checkpoint folder {checkpoint_dir} does not exist.")
        if (checkpoint_dir / "pretrained_model").is_dir():
            raise ValueError(
                f"{checkpoint_dir} holds a `pretrained_model` folder; save the calibration there, next to "
                "the policy's config.json, so `from_pretrained` finds it."
            )
        path = checkpoint_dir / OOD_CALIBRATION_FILENAME
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass overwrite=True to replace it.")
        # `threshold` is written for people reading the file; loading recomputes it. JSON has no infinity.
        payload = {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in (a.attribute for a in _BESIDE_THE_JSON)
        }
        payload = {
            key: _to_json_number(value) for key, value in {**payload, "threshold": self.threshold}.items()
        }
        for beside in _BESIDE_THE_JSON:
            statistics = getattr(self, beside.attribute)
            beside_path = checkpoint_dir / beside.filename
            if statistics is None:
                beside_path.unlink(missing_ok=True)  # a previous calibration's file no longer belongs here
                continue
            data = statistics.to_bytes()
            payload[beside.field] = {
                "file": beside.filename,
                **beside.description(statistics),
                "sha256": hashlib.sha256(data).hexdigest(),
            }
            beside_path.write_bytes(data)  # first: a reader that finds the JSON finds its statistics
        path.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "OODCalibration":
        """Reads a calibration from `ood_calibration.json` or from the checkpoint folder that holds it.

        Files written before the conformal fields existed read with `rule="mean_std"`, files written before
        the phase energy with `score="final_energy"`. Context statistics and neighbours are read from the files
        the JSON's `context_statistics` and `context_neighbours` name, beside it.
        """
        path = Path(path)
        if path.is_dir():
            path = path / OOD_CALIBRATION_FILENAME
        try:
            payload = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(payload, dict):
                raise TypeError(f"expected a JSON object, got {type(payload).__name__}")
            payload.pop("threshold", None)
            if payload.get("conformal_threshold") == "inf":
                payload["conformal_threshold"] = math.inf
            for beside in _BESIDE_THE_JSON:
                if beside.field in payload:
                    payload[beside.attribute] = _load_beside_the_json(path, beside, payload.pop(beside.field))
            return cls(**payload)
        except (json.JSONDecodeError, TypeError, ValueError) as e:
            json_names = {beside.attribute: beside.field for beside in _BESIDE_THE_JSON}
            fields = ", ".join(json_names.get(f.name, f.name) for f in dataclasses.fields(cls))
            raise ValueError(
                f"{path} is not a valid OOD calibration ({e}). Expected a JSON object with the fields "
                f"{fields} (mu_v, sigma_v required), as `OODCalibration.save` and `ebvla-ood-report "
                "--calibrate_to` write it: calibrate again, or remove the file."
            ) from e

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path) -> "OODCalibration":
        """Loads the calibration of a local checkpoint folder or of a Hugging Face Hub model repository."""
        if Path(pretrained_name_or_path).exists():
            return cls.load(pretrained_name_or_path)
        from huggingface_hub import hf_hub_download

        repo_id = str(pretrained_name_or_path)
        try:
            path = hf_hub_download(repo_id, OOD_CALIBRATION_FILENAME)
        except Exception as e:  # a mistyped local path reaches the Hub as an invalid repo id
            raise FileNotFoundError(
                f"No {OOD_CALIBRATION_FILENAME} in a local folder or Hub repo named {pretrained_name_or_path}; "
                "create it with `ebvla-ood-report --calibrate_to=...`."
            ) from e
        for beside in _BESIDE_THE_JSON:
            if (name := _file_named(Path(path), beside.field)) is None:
                continue
            try:
                hf_hub_download(repo_id, name)  # into the same snapshot folder, beside the JSON
            except Exception as e:
                raise ValueError(
                    f"The {OOD_CALIBRATION_FILENAME} of the Hub repo {repo_id} names its {beside.what} "
                    f"`{beside.field}.file` = {name!r}, which cannot be downloaded ({e}): upload it beside the "
                    "JSON, or calibrate again."
                ) from e
        return cls.load(path)


@dataclass(frozen=True)
class _BesideTheJSON:
    """A calibration attribute saved beside `ood_calibration.json` in a safetensors file the JSON names.

    Args:
        attribute: The `OODCalibration` field.
        field: The JSON field that names the file, with `description` and its SHA-256.
        filename: The file, beside the JSON.
        what: What it holds, for error messages.
        reader: Builds the attribute from the file's bytes (`from_bytes`).
        description: The numbers the JSON records about it, checked against the file on loading.
    """

    attribute: str
    field: str
    filename: str
    what: str
    reader: Callable[[bytes], "ContextStatistics | ContextNeighbours"]
    description: Callable[["ContextStatistics | ContextNeighbours"], dict[str, int]]


_BESIDE_THE_JSON = (
    _BesideTheJSON(
        "context",
        CONTEXT_FIELD,
        OOD_CONTEXT_FILENAME,
        "context statistics",
        ContextStatistics.from_bytes,
        lambda s: {"dim": s.dim, "n_chunks": s.n_chunks},
    ),
    _BesideTheJSON(
        "neighbours",
        NEIGHBOURS_FIELD,
        OOD_NEIGHBOURS_FILENAME,
        "context neighbours",
        ContextNeighbours.from_bytes,
        lambda s: {"dim": s.dim, "n_chunks": s.n_chunks, "k": s.k},
    ),
)


def _file_named(path: Path, json_field: str) -> str | None:
    """The file a calibration JSON's `json_field` names; None when it names none or cannot be read
    (`OODCalibration.load` then says what is wrong)."""
    try:
        entry = json.loads(path.read_text(encoding="utf-8")).get(json_field)
        return str(entry["file"])
    except (OSError, json.JSONDecodeError, AttributeError, TypeError, KeyError):
        return None


def _load_beside_the_json(
    path: Path, beside: _BesideTheJSON, entry: object
) -> "ContextStatistics | ContextNeighbours":
    """The attribute of a calibration JSON's entry (`context_statistics`, `context_neighbours`), checked
    against it: the file exists beside the JSON, has the recorded SHA-256, and holds what the entry says."""
    name_of = beside.field
    if not isinstance(entry, dict) or "file" not in entry or "sha256" not in entry:
        raise ValueError(f"`{name_of}` must be an object with the keys `file` and `sha256`, got {entry!r}")
    name = entry["file"]
    if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
        raise ValueError(f"`{name_of}.file` must be a file name beside the JSON, got {name!r}")
    beside_path = path.with_name(name)
    if not beside_path.is_file():
        raise ValueError(
            f"`{name_of}.file` names {beside_path}, which does not exist: the {beside.what} are saved beside "
            "the JSON and must travel with it"
        )
    data = beside_path.read_bytes()
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise ValueError(
            f"{beside_path} does not match `{name_of}.sha256`: it belongs to another calibration"
        )
    try:
        value = beside.reader(data)
    except ValueError as e:
        raise ValueError(f"{beside_path}: {e}") from e
    described = beside.description(value)
    keys = {"file", *described, "sha256"}
    if set(entry) != keys:
        raise ValueError(f"`{name_of}` must be an object with the keys {sorted(keys)}, got {entry!r}")
    recorded = {key: entry[key] for key in described}
    if described != recorded:
        raise ValueError(
            f"{beside_path} holds {beside.what} with {described}, but `{name_of}` says {recorded}"
        )
    return value


@dataclass(frozen=True)
class OODDecision:
    """The monitor's verdict on one energy score.

    Args:
        in_distribution: True when energy <= threshold; False (OOD) otherwise, including non-finite energy.
        energy: The score that was checked (a chunk's final energy or a rollout score).
        threshold: The threshold T it was compared to.
    """

    in_distribution: bool
    energy: float
    threshold: float

    @property
    def is_ood(self) -> bool:
        return not self.in_distribution


class EnergyOODMonitor:
    """Run-time OOD monitor: compares chunk scores, as the calibration defines them, to its threshold T.

    Per chunk, `check` compares each chunk score to T. Per rollout, `update` accumulates each environment's
    chunk scores and compares their running rollout score (the calibration's aggregation) to T, and
    `check_rollout` does the same for a finished rollout's chunks. The chunk score is the final energy, with
    a phase-energy calibration the final energy against the vanilla energy at the chunk's index, with a
    context-distance calibration the distance of the chunk's pooled context
    (`OODCalibration.chunk_score`): `update` and `check_rollout` count the chunks themselves, `check` needs
    the index; the context distance and the energy-and-context score need `context_features` everywhere. With
    the energy-and-context score a rollout's final energies and context distances are aggregated apart and
    combined after (`OODCalibration.score_rollout`).

    Example:
        monitor = EnergyOODMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
        actions, energy = policy.predict_action_chunk(batch, return_energy=True)
        if any(d.is_ood for d in monitor.update(energy.final_energy)):
            ...  # stop, ask for help, fall back to a safe policy
    """

    def __init__(self, calibration: OODCalibration):
        self.calibration = calibration
        # Per environment, the `OODCalibration.chunk_components` row of each chunk so far.
        self._histories: list[list[np.ndarray]] = []

    @classmethod
    def from_pretrained(
        cls, pretrained_name_or_path: str | Path, k: float | None = None
    ) -> "EnergyOODMonitor":
        """Builds a monitor from a checkpoint's `ood_calibration.json`, optionally with Eq. 5 at another k."""
        calibration = OODCalibration.from_pretrained(pretrained_name_or_path)
        return cls(calibration if k is None else calibration.with_k(k))

    @property
    def threshold(self) -> float:
        return self.calibration.threshold

    def _decide(self, energy: float) -> OODDecision:
        return OODDecision(not bool(exceeds(energy, self.threshold)[0]), float(energy), self.threshold)

    def check(
        self,
        final_energy: float | Tensor,
        chunk_index: int | None = None,
        context_features: ArrayLike | None = None,
    ) -> OODDecision | list[OODDecision]:
        """Checks chunk final energies: a scalar gives one decision, a (B,) tensor or array a list of B.

        `chunk_index` (the chunks' index in their episodes) is needed by a phase-energy calibration only,
        `context_features` ((D,) or (B, D) pooled contexts) by a context-distance calibration only.
        """
        scores = as_array(self.calibration.chunk_score(as_array(final_energy), chunk_index, context_features))
        if _ndim(final_energy) == 0:
            return self._decide(float(scores[0]))
        return [self._decide(e) for e in scores]

    def check_rollout(
        self, chunk_energies: ArrayLike, context_features: ArrayLike | None = None
    ) -> OODDecision:
        """Checks a rollout from its chunks' final energies (chunks 0, 1, ...), aggregated as calibrated.

        `context_features`, (N, D) one pooled context per chunk, is needed by a context-distance or an
        energy-and-context calibration.
        """
        energies = as_array(chunk_energies)
        components = self.calibration.chunk_components(energies, np.arange(energies.size), context_features)
        return self._decide(self.calibration.score_rollout(components))

    def update(
        self, final_energy: float | Tensor, context_features: ArrayLike | None = None
    ) -> list[OODDecision]:
        """Adds one chunk's score per environment and checks each environment's rollout so far.

        Args:
            final_energy: A float (one environment) or a (B,) tensor, one entry per environment.
            context_features: The chunk's pooled context per environment, (B, D), for a context-distance or an
                energy-and-context calibration.

        Returns:
            One decision per environment on its running rollout score.
        """
        energies = as_array(final_energy)
        if not self._histories:
            self._histories = [[] for _ in energies]
        if len(energies) != len(self._histories):
            raise ValueError(
                f"Expected {len(self._histories)} energies (one per environment), got {len(energies)}."
            )
        if context_features is not None and _ndim(context_features) == 1:
            context_features = _float64(context_features)[None]  # one environment
        # The environments step together: this is chunk len(history) of every one of them.
        chunk_index = len(self._histories[0])
        components = self.calibration.chunk_components(energies, chunk_index, context_features)
        for history, row in zip(self._histories, components, strict=True):
            history.append(row)
        return [
            self._decide(self.calibration.score_rollout(np.stack(history))) for history in self._histories
        ]

    def reset(self) -> None:
        """Forgets the accumulated scores; call it when the environments reset."""
        self._histories = []
