"""Fréchet distance between two sets of image features (float64 throughout).

    FD = ‖μ1 − μ2‖² + tr(Σ1 + Σ2 − 2 (Σ1 Σ2)^½)

(Dowson & Landau 1982; the FID of Heusel et al. 2017 is this with Inception-v3 pool features.
Here the features are whatever the caller gives, so results are named for their extractor,
e.g. ``fd_effnet_lite0`` — never "FID".)

tr((Σ1 Σ2)^½) is computed from a symmetric matrix so it stays real and stable:
Σ1 Σ2 is similar to Σ1^½ Σ2 Σ1^½ (PSD), so tr((Σ1 Σ2)^½) = Σ_i sqrt(λ_i(Σ1^½ Σ2 Σ1^½)), with
Σ1^½ and the eigenvalues from `eigh`, and eigenvalues at round-off level (below d·eps·λ_max,
negative ones included) set to 0. This holds for rank-deficient covariances, which is the normal case
with fewer samples than feature dimensions — where scipy's `sqrtm` of the non-symmetric
Σ1 Σ2 returns complex noise.

From features directly (`frechet_distance_features`) the same trace is the nuclear norm of
A1 A2ᵀ with A_i = (X_i − μ_i) / sqrt(n_i − 1), since Σ_i = A_iᵀ A_i: an n1×n2 problem instead
of d×d, exact, and what we use when samples are fewer than dimensions.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from lsd3d_usd.errors import InputError


class FewSamplesWarning(UserWarning):
    """Fewer samples than feature dimensions: the covariance is rank-deficient and the
    Fréchet distance is biased upwards (compare only values computed with equal counts)."""


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


def _clip_eig(w: np.ndarray) -> np.ndarray:
    """Eigenvalues of a PSD matrix with round-off removed: anything below d·eps·λ_max is 0
    (sqrt would turn 1e-16 noise on a rank-deficient matrix into 1e-8 per eigenvalue)."""
    tol = len(w) * np.finfo(np.float64).eps * max(float(np.max(np.abs(w), initial=0.0)), 0.0)
    return np.where(w > tol, w, 0.0)


def psd_sqrt(a: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric PSD matrix (round-off and negative eigenvalues
    clipped to 0)."""
    w, v = np.linalg.eigh(_sym(np.asarray(a, np.float64)))
    return (v * np.sqrt(_clip_eig(w))) @ v.T


def trace_sqrt_product(s1: np.ndarray, s2: np.ndarray) -> float:
    """tr((Σ1 Σ2)^½) for symmetric PSD Σ1, Σ2 via eigh of Σ1^½ Σ2 Σ1^½."""
    r = psd_sqrt(s1)
    w = np.linalg.eigvalsh(_sym(r @ np.asarray(s2, np.float64) @ r))
    return float(np.sqrt(_clip_eig(w)).sum())


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """Fréchet distance between N(μ1, Σ1) and N(μ2, Σ2); >= 0."""
    mu1, mu2 = np.asarray(mu1, np.float64).ravel(), np.asarray(mu2, np.float64).ravel()
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    d = mu1.shape[0]
    if mu2.shape != (d,) or s1.shape != (d, d) or s2.shape != (d, d):
        raise InputError(f"frechet_distance: shapes do not match: mu {mu1.shape}/{mu2.shape}, "
                         f"sigma {s1.shape}/{s2.shape}")
    for name, x in (("mu1", mu1), ("mu2", mu2), ("sigma1", s1), ("sigma2", s2)):
        if not np.all(np.isfinite(x)):
            raise InputError(f"frechet_distance: {name} has non-finite values")
    diff = mu1 - mu2
    fd = diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * trace_sqrt_product(s1, s2)
    return float(max(fd, 0.0))


def feature_stats(x) -> tuple[np.ndarray, np.ndarray]:
    """Mean and unbiased covariance (ddof 1; zeros for a single sample) of (n, d) features."""
    x = np.asarray(x, np.float64)
    if x.ndim != 2 or x.shape[0] < 1:
        raise InputError(f"features must be a non-empty (n, d) array, got shape {x.shape}")
    mu = x.mean(axis=0)
    if x.shape[0] == 1:
        return mu, np.zeros((x.shape[1], x.shape[1]))
    xc = x - mu
    return mu, xc.T @ xc / (x.shape[0] - 1)


@dataclass
class FDResult:
    value: float
    n1: int
    n2: int
    dims: int
    warning: str | None = None

    def to_json(self) -> dict:
        d = {"value": round(self.value, 6), "n": [self.n1, self.n2], "dims": self.dims}
        if self.warning:
            d["warning"] = self.warning
        return d


def frechet_distance_features(x1, x2, *, warn: bool = True) -> FDResult:
    """Fréchet distance between the Gaussians fitted to two feature sets (n_i, d).

    With fewer samples than dimensions the covariances are rank-deficient: the value is
    still exact for the fitted Gaussians (nuclear-norm form, see module doc) but biased, and
    a FewSamplesWarning says so (also recorded in the result)."""
    x1, x2 = np.asarray(x1, np.float64), np.asarray(x2, np.float64)
    if x1.ndim != 2 or x2.ndim != 2 or x1.shape[1] != x2.shape[1]:
        raise InputError(f"feature sets must be (n, d) with the same d, got {x1.shape} and {x2.shape}")
    if x1.shape[0] < 1 or x2.shape[0] < 1:
        raise InputError(f"feature sets must be non-empty, got {x1.shape[0]} and {x2.shape[0]} samples")
    if not (np.all(np.isfinite(x1)) and np.all(np.isfinite(x2))):
        raise InputError("feature sets contain non-finite values")
    (n1, d), n2 = x1.shape, x2.shape[0]
    msg = None
    if min(n1, n2) < d:
        msg = (f"Fréchet distance from {n1} and {n2} samples of {d}-d features: fewer samples "
               f"than dimensions, covariances are rank-deficient and the value is biased upwards; "
               f"compare only values computed with the same sample counts")
        if warn:
            warnings.warn(msg, FewSamplesWarning, stacklevel=2)
    mu1, mu2 = x1.mean(0), x2.mean(0)
    diff = mu1 - mu2
    if min(n1, n2) < d:
        a1 = (x1 - mu1) / np.sqrt(max(n1 - 1, 1))
        a2 = (x2 - mu2) / np.sqrt(max(n2 - 1, 1))
        tr1, tr2 = float((a1 * a1).sum()), float((a2 * a2).sum())
        cross = float(np.linalg.svd(a1 @ a2.T, compute_uv=False).sum()) if n1 > 1 and n2 > 1 else 0.0
        fd = max(diff @ diff + tr1 + tr2 - 2.0 * cross, 0.0)
    else:
        (_, s1), (_, s2) = feature_stats(x1), feature_stats(x2)
        fd = frechet_distance(mu1, s1, mu2, s2)
    return FDResult(float(fd), n1, n2, d, msg)
