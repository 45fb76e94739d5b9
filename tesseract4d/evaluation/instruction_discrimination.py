"""Instruction discrimination: does the network use the words, whatever its sampler makes of them?

The instruction contrast judges sampled clips, so it mixes two failures: a network that ignores the
instruction, and a sampler that loses what the network knew. This measure isolates the first. For a
counterfactual group (one scene, several instructions, each with its true future), the network makes
its one-step prediction of the clean clip from pure noise for every instruction of the group: exactly
the sampler's first look at the scene (the initial noise of the scene's draw, first frame and words
only, no guidance). An episode is *discriminated* when the prediction made from its own instruction
is closer to its true future than the predictions made from each other instruction of the group.

Closeness is the mean squared error in the network's space over the cells where the group's true
futures disagree (the top :data:`DISAGREE_SHARE` of cells by the spread of the group's futures), so
the arm's shared motion and the static background do not decide it. A network that ignores the words
makes the same prediction for every instruction and discriminates nothing (ties are not wins); chance
for a group of n distinct instructions is 1/n.

*Words over the noisy sample* asks the next question, what a sampler's later steps do: shown the
noisy sample of another future of its group (noise level :data:`SIBLING_T`, the group's noise), does
the network's prediction from an episode's own words land closer to that episode's future than to the
future it was shown? A denoiser that reads the future from its noisy sample and not from the words
sides with the sample; docs/research/evaluation.md, "Where a model fails", has what v2 does.
"""

from __future__ import annotations

import torch

# The cells where the group's true futures differ most (the share DISAGREE_SHARE of its latent cells):
# defined beside the training recipe (model/recipe.py).
from tesseract4d.model.recipe import DISAGREE_SHARE, disagreement_mask  # noqa: F401
from tesseract4d.model.codec import make_condition
from tesseract4d.intervals import wilson_interval

# The noise level at which words_over_sample shows an episode another future's noisy sample: the
# middle of sampling, where v2's samplers were seen to pull the instructed object back.
SIBLING_T = 0.5


@torch.no_grad()
def one_step_predictions(pipeline, clips: torch.Tensor, instructions: list[str], noise: torch.Tensor) -> torch.Tensor:
    """The network's clean-clip prediction from pure noise, without guidance, per instruction.

    clips: (n, T, 7, H, W) model-space clips at the pipeline's resolution and clip length (their first
    frames condition the prediction); noise: (1, t', c, h, w) network-space noise shared by the group.
    Returns (n, t', c, h, w): prediction i from first frame i and ``instructions[i]``.
    """
    n = clips.shape[0]
    first = pipeline.codec.encode(clips[:, :1].to(pipeline.device))  # (n, 1, c, h, w)
    cond = make_condition(first, noise.shape[1], pipeline.preset.condition)
    text = pipeline.text_encoder.encode(list(instructions)).to(pipeline.device)
    x_t = noise.to(pipeline.device).expand(n, *noise.shape[1:])
    return pipeline._predict_x0(x_t, 1.0, cond, torch.zeros_like(cond), text, torch.zeros_like(text), 1.0, 1.0)


@torch.no_grad()
def discrimination_errors(pipeline, clips: torch.Tensor, instructions: list[str], noise: torch.Tensor) -> torch.Tensor:
    """(n, n) errors E[a, j]: mean squared error, over the group's disagreement cells, between the
    one-step prediction made from instruction j and the true future of episode a (network space)."""
    x0 = pipeline.codec.encode(clips.to(pipeline.device)).float()  # (n, t', c, h, w)
    pred = one_step_predictions(pipeline, clips, instructions, noise).float()
    mask = disagreement_mask(x0)
    diff = (x0[:, None] - pred[None]) ** 2  # (a, j, t', c, h, w)
    return (diff * mask[None]).sum((2, 3, 4, 5)) / (mask.sum() * x0.shape[2])


@torch.no_grad()
def sibling_sample_predictions(pipeline, clips: torch.Tensor, instructions: list[str], noise: torch.Tensor,
                               t: float = SIBLING_T, x0: torch.Tensor | None = None) -> torch.Tensor:
    """(n, n, t', c, h, w): P[a, j] is the network's unguided clean-clip prediction from episode a's
    first frame and instruction, shown episode j's noisy sample ``(1 - t) x0_j + t noise`` (network
    space; noise (1, t', c, h, w) shared by the group). P[a, a] is an ordinary denoising step.
    ``x0``: the clips already encoded, when the caller has them."""
    n = clips.shape[0]
    if x0 is None:
        x0 = pipeline.codec.encode(clips.to(pipeline.device)).float()  # (n, t', c, h, w)
    first = pipeline.codec.encode(clips[:, :1].to(pipeline.device))  # (n, 1, c, h, w)
    cond = make_condition(first, noise.shape[1], pipeline.preset.condition)
    text = pipeline.text_encoder.encode(list(instructions)).to(pipeline.device)
    x_t = (1 - t) * x0 + t * noise.to(pipeline.device)
    rows = []
    for a in range(n):
        c = cond[a:a + 1].expand(n, *cond.shape[1:])
        e = text[a:a + 1].expand(n, *text.shape[1:])
        rows.append(pipeline._predict_x0(x_t, t, c, torch.zeros_like(c), e, torch.zeros_like(e), 1.0, 1.0).float())
    return torch.stack(rows)


def words_over_sample(pipeline, clips: torch.Tensor, instructions: list[str], noise: torch.Tensor,
                      t: float = SIBLING_T) -> list[bool]:
    """Per ordered pair (a, j) of a group's episodes with different instructions: shown j's noisy
    sample, is the prediction from a's words strictly closer to a's true future than to j's (squared
    error over the group's disagreement cells)? A network that follows the noisy sample over the words
    scores none; one that follows the words over it, all."""
    x0 = pipeline.codec.encode(clips.to(pipeline.device)).float()
    pred = sibling_sample_predictions(pipeline, clips, instructions, noise, t, x0=x0)
    mask = disagreement_mask(x0)[0]
    out = []
    for a, own in enumerate(instructions):
        for j, other in enumerate(instructions):
            if other != own:
                e_own = float(((pred[a, j] - x0[a]) ** 2 * mask).sum())
                e_shown = float(((pred[a, j] - x0[j]) ** 2 * mask).sum())
                out.append(e_own < e_shown)
    return out


def summarize_words_over_sample(judged: list[bool], t: float = SIBLING_T) -> dict:
    """{"pairs", "words", "share", "t", "wilson95"} of :func:`words_over_sample` judgments."""
    n, k = len(judged), sum(judged)
    return {"pairs": n, "words": k, "share": k / n if n else None, "t": t,
            "wilson95": list(wilson_interval(k, n)) if n else None}


def own_closest(errors: torch.Tensor, instructions: list[str]) -> list[bool | None]:
    """Per episode a: is its own instruction's prediction strictly the closest to its true future among
    the group's distinct instructions? None where the group has no other instruction than a's."""
    out: list[bool | None] = []
    for a, text in enumerate(instructions):
        others = [j for j, other in enumerate(instructions) if other != text]
        out.append(None if not others else bool(errors[a, a] < min(float(errors[a, j]) for j in others)))
    return out


def summarize_discrimination(judged: list[tuple[bool, int]]) -> dict:
    """{"episodes", "right", "share", "chance", "wilson95"} over (right, distinct instructions in the
    group) pairs; chance is the mean of 1 / distinct instructions."""
    n = len(judged)
    right = sum(r for r, _ in judged)
    return {"episodes": n, "right": right, "share": right / n if n else None,
            "chance": sum(1.0 / k for _, k in judged) / n if n else None,
            "wilson95": list(wilson_interval(right, n)) if n else None}
