"""DBoW2-style bags of binary (and float) words: vocabulary tree, inverse/direct index database, loop detection.

* `placerec.retrieval.dbow.vocabulary` — `Vocabulary` (tree, transform, L1 score), `train_vocabulary`.
* `placerec.retrieval.dbow.kmeans` — the vectorised hierarchical k-means++ behind training.
* `placerec.retrieval.dbow.database` — `BowDatabase`: inverse index (CSR + append buffer), direct index, queries.
* `placerec.retrieval.dbow.loop_detector` — DLoopDetector's options: normalised score, islands, temporal check.
* `placerec.retrieval.dbow.io` — the compact binary vocabulary format and the ORB-SLAM2/DBoW2 text format.

Training a vocabulary from an experiment config (``placerec train-vocab``) is orchestration and lives in
`placerec.artifacts.vocabulary`.

Names below are imported lazily.
"""

from __future__ import annotations

from placerec._lazy import lazy_exports

__all__ = [
    "BowVector",
    "Vocabulary",
    "l1_score",
    "train_vocabulary",
    "BowDatabase",
    "QueryResults",
    "LoopDetectorParams",
    "normalised_results",
    "load_vocabulary",
    "save_vocabulary",
    "read_text_vocabulary",
    "write_text_vocabulary",
]

_LAZY = {
    "BowVector": "vocabulary",
    "Vocabulary": "vocabulary",
    "l1_score": "vocabulary",
    "train_vocabulary": "vocabulary",
    "BowDatabase": "database",
    "QueryResults": "database",
    "LoopDetectorParams": "loop_detector",
    "normalised_results": "loop_detector",
    "load_vocabulary": "io",
    "save_vocabulary": "io",
    "read_text_vocabulary": "io",
    "write_text_vocabulary": "io",
}


__getattr__ = lazy_exports(__name__, _LAZY)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
