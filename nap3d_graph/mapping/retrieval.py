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

__all__ = ["Vocabulary", "vlad", "similarities"]


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
