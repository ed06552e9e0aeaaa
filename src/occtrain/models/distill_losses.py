"""Knowledge distillation from a frozen teacher: logit KL at a temperature and SparseOccVLA's
feature distillation (a projection + LayerNorm of the student's states, pulled towards the
teacher's LayerNorm-ed states by a cosine loss)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


class FeatureProjector(torch.nn.Module):
    """Student hidden states -> the teacher's width, then LayerNorm (SparseOccVLA's distillation head)."""

    def __init__(self, student_dim: int, teacher_dim: int):
        super().__init__()
        self.proj = torch.nn.Linear(student_dim, teacher_dim)
        self.norm = torch.nn.LayerNorm(teacher_dim)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.norm(self.proj(hidden))


def distillation_losses(
    student_logits: torch.Tensor,
    teacher_logits: torch.Tensor,
    student_feat: torch.Tensor,
    teacher_hidden: torch.Tensor,
    valid: torch.Tensor,
    temperature: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """KL(teacher || student) at temperature T (times T^2) and 1 - cosine of the features,
    both averaged over the ``valid`` (non-padding) positions."""
    t = temperature
    log_p_s = F.log_softmax(student_logits[valid].float() / t, dim=-1)
    log_p_t = F.log_softmax(teacher_logits[valid].float() / t, dim=-1)
    kl = F.kl_div(log_p_s, log_p_t, log_target=True, reduction="batchmean") * t * t
    target = F.layer_norm(teacher_hidden[valid].float(), teacher_hidden.shape[-1:])
    cos = 1.0 - F.cosine_similarity(student_feat[valid].float(), target, dim=-1).mean()
    return kl, cos
