"""The vanilla statistics the chunk scores measure against, each fitted on calibration rollouts.

- `PhaseStatistics`: mu_v[t] and sigma_v[t], the vanilla final energy at each chunk index t (the phase energy's
  reference).
- `ChunkWindow`: the same statistics of the vanilla rollouts' running score after each of their first N chunks, and
  the window score they define (the OOD calibration's rollout score at run time).
- `ContextStatistics`: the mean mu_c and the precision P of the vanilla pooled contexts, P the inverse of their
  Ledoit-Wolf shrunk covariance (the context distance's reference).
- `ContextNeighbours`: the vanilla pooled contexts themselves, standardized (the context k-NN distance's).
- `CombinedStatistics`: the vanilla rollout scores' mean and std of the final energy and of the context distance
  (the energy-and-context score's standardization).

The context statistics and neighbours are arrays of D and D x D numbers (D = 896 for the VLM): they are saved in
safetensors files beside `ood_calibration.json` (`to_bytes`, `from_bytes`). `scores.py` turns each into a
chunk score.
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import safetensors.numpy
import torch
from safetensors import SafetensorError
from torch import Tensor

from .threshold import ArrayLike, MeanStd, as_array

# Which nearest vanilla context the context k-NN distance measures to, unless told. The nearest: vanilla
# rollouts differ mostly by where the scene's objects start, so a vanilla chunk has a close twin among the
# calibration chunks while a shifted one does not; from the 5th the spread of starting scenes drowns a small
# shift (a distractor: AUROC 0.65 / 0.74 on the first 3 chunks at k = 5, 0.98 / 1.00 at k = 1;
# research/docs/benchmarks_history.md, section 6).
DEFAULT_KNN_K = 1
# sigma_v[t] is at least this fraction of the pooled sigma of all vanilla chunk energies.
PHASE_SIGMA_FLOOR = 0.1
# And at least this, so that a calibration of identical energies still divides by a positive number.
MIN_SIGMA = 1e-12


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
        """Fits on the final energies of vanilla episodes, each in chunk order (index t is entry t; NaN where an
        episode has no chunk t, as `energies_by_index` writes it).

        Raises:
            ValueError: No finite energy at all.
        """
        series = [as_array(e) for e in episode_energies]
        pooled = np.concatenate(series) if series else np.zeros(0)
        pooled = pooled[np.isfinite(pooled)]
        if pooled.size == 0:
            raise ValueError(
                "Cannot fit phase statistics without a finite vanilla value (a final energy, E_c)."
            )
        floor = max(PHASE_SIGMA_FLOOR * float(pooled.std()), MIN_SIGMA)
        previous = (float(pooled.mean()), max(float(pooled.std()), floor))
        # One row per episode, NaN past its end: column t holds the episodes' chunk-t energies in episode order,
        # the same values in the same order as a loop over the episodes would gather (so the same mean and std),
        # without a Python step per episode and index (a leave-one-out report fits this thousands of times).
        by_index = np.full((len(series), max(len(s) for s in series)), np.nan)
        for row, energies in zip(by_index, series, strict=True):
            row[: len(energies)] = energies
        means, stds = [], []
        for column in by_index.T:
            at_t = column[np.isfinite(column)]
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


@dataclass(frozen=True)
class ChunkWindow:
    """The window score of a rollout's first N chunks: one score for the N decisions a run-time monitor makes.

    After its n-th chunk a rollout has the running score s_n (its chunk scores so far, aggregated). A T fitted on
    the calibration rollouts' s_N alone holds its false-alarm rate at chunk N only: s_1 and s_2 spread more, and
    compared to the same T they flag many more vanilla rollouts early. The window score

        W = max_{n <= min(N, chunks so far)} (s_n - mu_n) / sigma_n

    standardizes each s_n by mu_n and sigma_n of the calibration rollouts' s_n (`PhaseStatistics` of the running
    scores, n at index n - 1, with its floor on sigma), so a T fitted on the calibration rollouts' W bounds the share
    of in-distribution rollouts alarmed at any of their first N chunks (with the conformal rule, at most alpha).
    W stops changing after chunk N: the decision stands.

    Args:
        running: mu_n and sigma_n for n = 1 .. N.
    """

    running: PhaseStatistics

    @property
    def chunks(self) -> int:
        """N, the chunks the window spans."""
        return len(self.running.mean)

    @classmethod
    def fit(cls, running_scores: ArrayLike) -> "ChunkWindow":
        """Fits on (R, N) calibration running scores (row r: s_1 .. s_N of rollout r); non-finite ones are left
        out as `PhaseStatistics.fit` leaves them."""
        return cls(PhaseStatistics.fit(list(_running_matrix(running_scores))))

    def score(self, running_scores: ArrayLike) -> float:
        """W of one rollout from its running scores s_1 .. s_n (n >= 1; the first N count). NaN if one is NaN."""
        running = as_array(running_scores)[: self.chunks]
        if running.size == 0:
            raise ValueError("The window score needs the running score of at least one chunk.")
        z = self.running.z(running, np.arange(running.size))
        return float(np.nan if np.isnan(z).any() else z.max())

    def scores(self, running_scores: ArrayLike) -> np.ndarray:
        """(R,) W of each row of (R, N) running scores."""
        return np.array([self.score(row) for row in _running_matrix(running_scores, self.chunks)])

    @staticmethod
    def leave_one_out_scores(running_scores: ArrayLike) -> np.ndarray:
        """(R,) W of each calibration rollout standardized by the window of the other R - 1, as a new rollout
        would be (its own s_n would pull mu_n toward it). With R = 1, the window of the one rollout."""
        running = _running_matrix(running_scores)
        if running.shape[0] == 1:
            return ChunkWindow.fit(running).scores(running)
        return np.array(
            [
                ChunkWindow.fit(np.delete(running, r, axis=0)).score(running[r])
                for r in range(running.shape[0])
            ]
        )


def _running_matrix(running_scores: ArrayLike, chunks: int | None = None) -> np.ndarray:
    running = (
        running_scores.detach().to("cpu", torch.float64).numpy()
        if isinstance(running_scores, Tensor)
        else np.asarray(running_scores, dtype=np.float64)
    )
    if running.ndim != 2 or running.shape[1] < 1 or (chunks is not None and running.shape[1] != chunks):
        expected = "N >= 1" if chunks is None else f"N = {chunks}"
        raise ValueError(
            f"Running scores must be (R, {expected}): s_1 .. s_N of each rollout; got shape {running.shape}."
        )
    return running


def energies_by_index(final_energies: ArrayLike, chunk_indices: ArrayLike) -> np.ndarray:
    """One episode's final energies as a series indexed by chunk index, NaN where a chunk is missing (which
    `PhaseStatistics.fit` leaves out like any non-finite energy)."""
    indices = np.asarray(chunk_indices, dtype=np.int64)
    series = np.full(int(indices.max(initial=-1)) + 1, np.nan)
    series[indices] = as_array(final_energies)
    return series


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

    @classmethod
    def fit_without(cls, features: ArrayLike, excluded: np.ndarray) -> "ContextStatistics":
        """Fits on the (N, D) features outside the (N,) bool `excluded` rows (a calibration episode's own
        chunks); with fewer than two rows left, on all of them."""
        if np.any(excluded) and np.sum(~excluded) >= 2:
            features = float64(features)[~excluded]
        return cls.fit(features)

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
        """The safetensors file saved beside the calibration (`scores.CONTEXT_FILE`): mu_c and P in float64."""
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
        return cls(features, features.mean(axis=0), np.maximum(features.std(axis=0), MIN_SIGMA), k)

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
        """The safetensors file beside the calibration (`scores.NEIGHBOURS_FILE`): the features in float32, their
        mean and std in float64."""
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
        return cls((energy.mean, context.mean), (max(energy.std, MIN_SIGMA), max(context.std, MIN_SIGMA)))

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
    features = float64(features)
    if features.ndim != 2 or features.shape[0] < 2:
        raise ValueError(f"Context features to fit must be (N >= 2, D), got shape {features.shape}.")
    if not np.all(np.isfinite(features)):
        raise ValueError(f"Cannot fit {what} on non-finite context features.")
    return features


def _context_features(features: ArrayLike, dim: int, score: str) -> np.ndarray:
    """(N, D) float64 pooled contexts from (N, D) or one (D,); raises a ValueError naming the expected D."""
    features = float64(features)
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


def float64(values: ArrayLike) -> np.ndarray:
    """Any array or tensor as a float64 array of the same shape (tensors detached, on the CPU)."""
    if isinstance(values, Tensor):
        values = values.detach().to("cpu", torch.float64).numpy()
    return np.asarray(values, dtype=np.float64)
