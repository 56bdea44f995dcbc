"""Build an ORB bag-of-words vocabulary in DBoW2's text format (what ORB-SLAM3 loads).

ORB-SLAM3's own ``ORBvoc.txt`` is not available offline, so this trains one from images:

1. ORB descriptors from every image (OpenCV ``ORB_create`` with ORB-SLAM's extractor
   settings: 1000 features, scale factor 1.2, 8 levels; grey images).
2. A hierarchical k-majority tree (branching ``k``, depth ``L``; binary descriptors,
   Hamming distance), built level by level with all nodes of a level clustered at once
   (numpy, vectorised): k-means++ seeding, then assignment / bitwise-majority update
   until no assignment changes (or ``--max-iter``). As in DBoW2, a node with at most ``k``
   descriptors gets one leaf per descriptor, and a cluster with one descriptor is a leaf.
3. Leaf (word) weights by IDF, ``log(N_images / N_images_containing_word)``, counted by
   passing every training descriptor down the finished tree; inner nodes weigh 0.
4. DBoW2's text format, as read by ORB-SLAM3's ``TemplatedVocabulary::loadFromTextFile``:
   first line ``k L scoringType weightingType`` (``0 0``: L1-norm scoring, TF-IDF
   weighting), then one line per node after the root, parents before children:
   ``parentId isLeaf d0 ... d31 weight`` (descriptor bytes as decimal ints). The file has
   no trailing newline: the loader reads lines until EOF and would turn an empty last line
   into a spurious child of the root.

    python benchmarks/orbslam3/vocabulary.py --out /tmp/orbslam3/ORBvoc_built.txt \\
        --images '../shared/data/7scenes/redkitchen/*.color.jpg' \\
        --images '../shared/data/tum/rgbd_dataset_freiburg1_xyz/rgb/*.png'

A JSON sidecar (``<out>.json``) records the images, counts, build time and the file's sha256.
"""

from __future__ import annotations

import argparse
import glob
import hashlib
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
FAR = np.uint16(1000)  # larger than any Hamming distance between 256-bit descriptors


def orb_descriptors(paths: list[str], n_features: int = 1000, scale: float = 1.2,
                    levels: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(D, 32) uint8 descriptors of all images and the (D,) image index of each."""
    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=scale, nlevels=levels)
    descs, owner = [], []
    for i, p in enumerate(paths):
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"{p}: cannot read image")
        _, d = orb.detectAndCompute(img, None)
        if d is None:
            continue
        descs.append(d)
        owner.append(np.full(len(d), i, dtype=np.int32))
    return np.concatenate(descs), np.concatenate(owner)


def hamming_to_sets(desc: np.ndarray, sets: np.ndarray, valid: np.ndarray,
                    chunk: int = 40000) -> np.ndarray:
    """Distance of each desc[i] (n, 32) to each of sets[i] (n, k, 32); FAR where not valid[i]."""
    out = np.empty(sets.shape[:2], dtype=np.uint16)
    for a in range(0, len(desc), chunk):
        b = min(a + chunk, len(desc))
        x = np.bitwise_xor(desc[a:b, None, :], sets[a:b])
        out[a:b] = POPCOUNT[x].sum(axis=2, dtype=np.uint16)
    out[~valid] = FAR
    return out


def segment_pick(weights: np.ndarray, starts: np.ndarray, counts: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One index per segment drawn with probability proportional to ``weights`` inside it;
    also whether the segment had any weight."""
    cs = np.cumsum(weights, dtype=np.float64)
    before = np.where(starts > 0, cs[np.maximum(starts - 1, 0)], 0.0)
    total = cs[starts + counts - 1] - before
    target = before + rng.random(len(starts)) * total
    pick = np.searchsorted(cs, target, side="right")
    pick = np.clip(pick, starts, starts + counts - 1)
    return pick, total > 0


def k_majority(desc: np.ndarray, bits: np.ndarray, starts: np.ndarray, counts: np.ndarray,
               k: int, rng: np.random.Generator, max_iter: int):
    """Cluster each segment ``starts[g]:starts[g]+counts[g]`` of ``desc`` (sorted by group)
    into at most k clusters. Returns labels (n,), centers (G, k, 32), valid (G, k)."""
    n, G = len(desc), len(starts)
    gid = np.repeat(np.arange(G), counts)
    centers = np.zeros((G, k, 32), dtype=np.uint8)
    valid = np.zeros((G, k), dtype=bool)
    # k-means++ seeding, all groups at once
    first = starts + (rng.random(G) * counts).astype(np.int64)
    centers[:, 0] = desc[first]
    valid[:, 0] = True
    min_d = POPCOUNT[np.bitwise_xor(desc, centers[gid, 0])].sum(axis=1, dtype=np.int64)
    for c in range(1, k):
        pick, ok = segment_pick((min_d.astype(np.float64)) ** 2, starts, counts, rng)
        centers[ok, c] = desc[pick[ok]]
        valid[:, c] = ok
        d = POPCOUNT[np.bitwise_xor(desc, centers[gid, c])].sum(axis=1, dtype=np.int64)
        min_d = np.where(ok[gid], np.minimum(min_d, d), min_d)
    labels = np.full(n, -1, dtype=np.int64)
    for _ in range(max_iter):
        dist = hamming_to_sets(desc, centers[gid], valid[gid])
        new = dist.argmin(axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        # bitwise majority of each cluster: bit set when at least ceil(n/2) members have it
        cid = gid * k + labels
        order = np.argsort(cid, kind="stable")
        cid_sorted = cid[order]
        uniq, first_row, members = np.unique(cid_sorted, return_index=True, return_counts=True)
        new_bits = np.empty((len(uniq), 256), dtype=bool)
        row_chunk = 200000
        u = 0
        while u < len(uniq):
            # clusters u..v-1, whose rows span at most row_chunk (at least one cluster)
            v = int(np.searchsorted(first_row, first_row[u] + row_chunk, side="left"))
            v = max(v, u + 1)
            r0 = first_row[u]
            r1 = first_row[v] if v < len(uniq) else n
            sums = np.add.reduceat(bits[order[r0:r1]], first_row[u:v] - r0, axis=0, dtype=np.int32)
            need = (members[u:v] + 1) // 2
            new_bits[u:v] = sums >= need[:, None]
            u = v
        valid[:] = False
        g_of, c_of = uniq // k, uniq % k
        valid[g_of, c_of] = True
        centers[g_of, c_of] = np.packbits(new_bits, axis=1)
    return labels, centers, valid


class Tree:
    def __init__(self):
        self.parent = [np.array([-1])]
        self.desc = [np.zeros((1, 32), dtype=np.uint8)]
        self.leaf = [np.array([False])]
        self.size = 1

    def add(self, parent: np.ndarray, desc: np.ndarray, leaf: np.ndarray) -> np.ndarray:
        ids = np.arange(self.size, self.size + len(parent))
        self.parent.append(np.asarray(parent))
        self.desc.append(np.asarray(desc, dtype=np.uint8))
        self.leaf.append(np.asarray(leaf, dtype=bool))
        self.size += len(parent)
        return ids

    def arrays(self):
        return (np.concatenate(self.parent), np.concatenate(self.desc), np.concatenate(self.leaf))


def build_tree(desc: np.ndarray, k: int, L: int, rng: np.random.Generator, max_iter: int,
               log=print) -> Tree:
    tree = Tree()
    bits = np.unpackbits(desc, axis=1)
    idx = np.arange(len(desc))
    node = np.zeros(len(desc), dtype=np.int64)
    for level in range(1, L + 1):
        if len(idx) == 0:
            break
        t0 = time.time()
        order = np.argsort(node, kind="stable")
        idx, node = idx[order], node[order]
        groups, starts, counts = np.unique(node, return_index=True, return_counts=True)
        small = counts <= k
        # small nodes: one leaf per descriptor
        rows_small = np.repeat(small, counts)
        tree.add(node[rows_small], desc[idx[rows_small]], np.ones(rows_small.sum(), dtype=bool))
        # large nodes: k-majority
        rows = ~rows_small
        if not rows.any():
            idx = idx[:0]
            break
        l_idx = idx[rows]
        l_counts = counts[~small]
        l_starts = np.concatenate([[0], np.cumsum(l_counts)[:-1]])
        labels, centers, valid = k_majority(desc[l_idx], bits[l_idx], l_starts, l_counts, k, rng, max_iter)
        gid = np.repeat(np.arange(len(l_counts)), l_counts)
        cid = gid * k + labels
        members = np.bincount(cid, minlength=len(l_counts) * k).reshape(-1, k)
        keep = valid & (members > 0)
        g_of, c_of = np.nonzero(keep)  # row-major: children of one parent stay together
        child_members = members[g_of, c_of]
        is_leaf = (child_members == 1) | (level == L)
        ids = tree.add(groups[~small][g_of], centers[g_of, c_of], is_leaf)
        child_id = np.full((len(l_counts), k), -1, dtype=np.int64)
        child_id[g_of, c_of] = ids
        new_node = child_id[gid, labels]
        go_on = ~np.isin(new_node, ids[is_leaf])
        idx, node = l_idx[go_on], new_node[go_on]
        log(f"  level {level}: {len(groups)} nodes split ({(~small).sum()} clustered), "
            f"{tree.size} nodes so far, {len(idx)} descriptors go deeper ({time.time() - t0:.1f} s)")
    return tree


def transform(desc: np.ndarray, parent: np.ndarray, ndesc: np.ndarray, leaf: np.ndarray, k: int,
              chunk: int = 100000) -> np.ndarray:
    """Leaf node of each descriptor, descending as DBoW2 does (first nearest child wins)."""
    n_nodes = len(parent)
    children = np.full((n_nodes, k), -1, dtype=np.int64)
    order = np.argsort(parent[1:], kind="stable") + 1
    par = parent[order]
    start = np.searchsorted(par, par, side="left")
    slot = np.arange(len(order)) - start
    children[par, slot] = order
    out = np.zeros(len(desc), dtype=np.int64)
    for a in range(0, len(desc), chunk):
        d = desc[a:a + chunk]
        cur = np.zeros(len(d), dtype=np.int64)
        active = ~leaf[cur]
        while active.any():
            ii = np.nonzero(active)[0]
            ch = children[cur[ii]]
            dist = hamming_to_sets(d[ii], ndesc[np.maximum(ch, 0)], ch >= 0)
            cur[ii] = ch[np.arange(len(ii)), dist.argmin(axis=1)]
            active[ii] = ~leaf[cur[ii]]
        out[a:a + chunk] = cur
    return out


def write_text(path: Path, k: int, L: int, parent, ndesc, leaf, weight) -> None:
    lines = [f"{k} {L} 0 0"]
    for i in range(1, len(parent)):
        lines.append(f"{parent[i]} {int(leaf[i])} " + " ".join(map(str, ndesc[i].tolist()))
                     + f" {weight[i]:.6g}")
    path.write_text("\n".join(lines))  # no trailing newline (see module docstring)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", action="append", required=True, help="glob (repeatable)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("-k", type=int, default=10)
    ap.add_argument("-L", type=int, default=6)
    ap.add_argument("--max-descriptors", type=int, default=0, help="random sample for the tree (0: all)")
    ap.add_argument("--max-iter", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    t0 = time.time()
    paths = sorted(p for g in args.images for p in glob.glob(g))
    if not paths:
        raise SystemExit("no images matched")
    desc, owner = orb_descriptors(paths)
    print(f"{len(paths)} images, {len(desc)} ORB descriptors ({time.time() - t0:.1f} s)")
    rng = np.random.default_rng(args.seed)
    train = desc
    if args.max_descriptors and len(desc) > args.max_descriptors:
        train = desc[np.sort(rng.choice(len(desc), args.max_descriptors, replace=False))]
        print(f"tree from a random sample of {len(train)} descriptors")
    t1 = time.time()
    tree = build_tree(train, args.k, args.L, rng, args.max_iter)
    parent, ndesc, leaf = tree.arrays()
    print(f"tree: {len(parent) - 1} nodes, {leaf.sum()} words ({time.time() - t1:.1f} s)")
    # IDF over images, every descriptor counted
    word_node = transform(desc, parent, ndesc, leaf, args.k)
    pairs = np.unique(owner.astype(np.int64) * len(parent) + word_node)
    n_img = np.bincount(pairs % len(parent), minlength=len(parent))
    n_docs = len(np.unique(owner))
    weight = np.zeros(len(parent))
    has = leaf & (n_img > 0)
    weight[has] = np.log(n_docs / n_img[has])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out, args.k, args.L, parent, ndesc, leaf, weight)
    sha = hashlib.sha256(args.out.read_bytes()).hexdigest()
    meta = {
        "file": str(args.out), "sha256": sha, "k": args.k, "L": args.L,
        "scoring": "L1-norm (0)", "weighting": "TF-IDF (0)",
        "orb": {"nfeatures": 1000, "scaleFactor": 1.2, "nlevels": 8, "image": "greyscale", "opencv": cv2.__version__},
        "images": len(paths), "image_globs": args.images, "image_paths": paths,
        "descriptors": int(len(desc)), "tree_descriptors": int(len(train)),
        "nodes": int(len(parent) - 1), "words": int(leaf.sum()),
        "words_seen": int(has.sum()), "max_iter": args.max_iter, "seed": args.seed,
        "seconds": round(time.time() - t0, 1),
    }
    Path(str(args.out) + ".json").write_text(json.dumps(meta, indent=1))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB, {leaf.sum()} words, "
          f"{time.time() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
