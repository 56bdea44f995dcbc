"""A global descriptor per image, for loop candidates and relocalisation by appearance.

Chosen: VLAD (Jegou et al., CVPR 2010) over the matcher's own local descriptors (XFeat's
64-D learned ones, or SIFT's), with a small vocabulary clustered from the survey's own
keyframes. Why: the features are detected anyway for the verification that follows, so the
descriptor costs a few milliseconds; no package on the registry ships a place-recognition
network's weights inside its wheel (NetVLAD and its successors download them at first use,
which cannot happen here); and a vocabulary of the place itself separates its views better
than a generic one (the map is one room, not a city). Intra-normalisation and power
normalisation keep a repeated texture from dominating (Arandjelovic and Zisserman, CVPR 2013).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Vocabulary", "vlad", "similarities", "shared_matches"]


@dataclass
class Vocabulary:
    """``centres`` (K, D) float32: cluster centres of local descriptors."""

    centres: np.ndarray

    @classmethod
    def fit(cls, descriptors: list[np.ndarray], k: int = 32, seed: int = 0, sample: int = 20000) -> "Vocabulary":
        """k-means (OpenCV, k-means++ seeding, 3 attempts) over at most ``sample`` of the
        descriptors of every image in ``descriptors`` (each (Ni, D))."""
        import cv2

        stacked = np.concatenate([d for d in descriptors if len(d)], axis=0).astype(np.float32)
        if len(stacked) < k:
            raise ValueError(f"too few local descriptors ({len(stacked)}) for a vocabulary of {k}")
        rng = np.random.default_rng(seed)
        if len(stacked) > sample:
            stacked = stacked[rng.choice(len(stacked), sample, replace=False)]
        cv2.setRNGSeed(seed)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
        _, _, centres = cv2.kmeans(stacked, k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
        return cls(centres.astype(np.float32))


def vlad(descriptors: np.ndarray, vocabulary: Vocabulary) -> np.ndarray:
    """The VLAD vector (K * D,) of one image's local descriptors (N, D): per centre, the sum of
    its descriptors' residuals, each block L2-normalised, signed square root, L2-normalised
    (zeros when the image has no descriptor)."""
    centres = vocabulary.centres
    out = np.zeros_like(centres)
    descriptors = np.asarray(descriptors, dtype=np.float32)
    if len(descriptors):
        d2 = ((descriptors[:, None, :] - centres[None]) ** 2).sum(-1)
        nearest = np.argmin(d2, axis=1)
        np.add.at(out, nearest, descriptors - centres[nearest])
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, norms, out=np.zeros_like(out), where=norms > 0)
    out = np.sign(out) * np.sqrt(np.abs(out))
    flat = out.ravel()
    norm = np.linalg.norm(flat)
    return flat / norm if norm > 0 else flat


def similarities(query: np.ndarray, database: np.ndarray) -> np.ndarray:
    """Cosine similarity of VLAD vectors: query (D,) against database (M, D) -> (M,)."""
    return np.asarray(database) @ np.asarray(query)


def shared_matches(a: np.ndarray, b: np.ndarray, ratio: float = 0.8) -> int:
    """How many distinctive matches two images' local descriptors a (Na, D) and b (Nb, D)
    share: mutual nearest neighbours in Euclidean distance whose nearest is below ``ratio``
    times the second nearest (Lowe's test). For ranking candidates, not for an alignment: one
    float32 distance matrix, about 2 ms for two images of 800 XFeat features, where the
    matcher's own pairing (float64, sorted by ambiguity) takes several times that."""
    a = np.asarray(a, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32)
    if len(a) < 2 or len(b) < 2:
        return 0
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2.0 * (a @ b.T)  # (Na, Nb)
    nearest_b = np.argmin(d2, axis=1)
    mutual = np.flatnonzero(np.argmin(d2, axis=0)[nearest_b] == np.arange(len(a)))
    two = np.sqrt(np.clip(np.partition(d2[mutual], 1, axis=1)[:, :2], 0.0, None))
    return int(np.sum(two[:, 0] < ratio * two[:, 1]))
