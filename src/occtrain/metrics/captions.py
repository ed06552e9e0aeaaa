"""Caption / chain-of-thought text metrics, computed by the COCO caption evaluation code itself.

``pycocoevalcap`` supplies the PTB tokenisation (Stanford CoreNLP, lower-cased,
punctuation dropped), corpus-level BLEU-1..4 with the closest reference length, METEOR
1.5, ROUGE-L (beta 1.2) and CIDEr-D (n=4, sigma=6, document frequencies from the
evaluated references, x10). Its tokeniser and METEOR are Java programs: without ``java``
on the PATH, :meth:`CaptionMetric.compute` raises rather than report a different number.
"""

from __future__ import annotations

import atexit
import contextlib
import io
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities.data import dim_zero_cat
from torchmetrics.utilities.distributed import gather_all_tensors

from occtrain.errors import OcctrainError

#: Output keys, exactly as pycocoevalcap names them.
CAPTION_KEYS = ("Bleu_1", "Bleu_2", "Bleu_3", "Bleu_4", "METEOR", "ROUGE_L", "CIDEr")


def _encode(records: list[str]) -> Tensor:
    """Strings -> one uint8 tensor of their UTF-8 bytes, each record ended by a NUL byte.

    The records are JSON, which escapes control characters, so NUL never occurs inside one.
    """
    blob = b"".join(r.encode("utf-8") + b"\0" for r in records)
    return torch.frombuffer(bytearray(blob), dtype=torch.uint8) if blob else torch.zeros(0, dtype=torch.uint8)


def _decode(data: Tensor) -> list[str]:
    return [r.decode("utf-8") for r in data.cpu().numpy().tobytes().split(b"\0")[:-1]]


def _gather_bytes(tensor: Tensor, group: Any = None) -> list[Tensor]:
    # torchmetrics stands in a float32 tensor for the state of a process that saw no sample;
    # every process must send bytes for the gather to line up.
    return gather_all_tensors(tensor.to(torch.uint8), group=group)


@contextlib.contextmanager
def _java_stderr_kept_aside() -> Any:
    """The PTB tokeniser's Java process reports its speed on the inherited stderr at every
    call; keep that out of a run's log, and show it only if the tokeniser fails."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        except BaseException:
            os.dup2(saved, 2)
            held.seek(0)
            sys.stderr.write(held.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)


_METEOR: Any = None


def _meteor(factory: Any) -> Any:
    """One METEOR scorer per process, started on first use and stopped at exit: its Java
    program takes seconds to load its paraphrase tables, and a validation scores captions
    several times (each text task and its baseline). Scores do not depend on earlier calls."""
    global _METEOR
    if _METEOR is None or _METEOR.meteor_p.poll() is not None:
        _METEOR = factory()
        atexit.register(_stop_meteor, _METEOR)
    return _METEOR


def _stop_meteor(meteor: Any) -> None:
    meteor.meteor_p.kill()
    meteor.meteor_p.wait()


def start_meteor() -> None:
    """Start METEOR's Java program now, in the background, where Java and pycocoevalcap are
    there: it spends about ten seconds loading its paraphrase tables, which an evaluation
    can overlap with generating the captions instead of waiting for them at the end."""
    if _METEOR is not None or shutil.which("java") is None:
        return
    try:
        from pycocoevalcap.meteor.meteor import Meteor
    except ImportError:
        return  # coco_caption_scores says what to install, when it is asked for scores
    _meteor(Meteor)


def coco_caption_scores(predictions: dict[str, str], references: dict[str, list[str]]) -> dict[str, float]:
    """pycocoevalcap's BLEU-1..4, METEOR, ROUGE-L and CIDEr-D for ``{id: caption}`` against ``{id: [refs]}``."""
    if shutil.which("java") is None:
        raise OcctrainError(
            "caption metrics need Java (pycocoevalcap's PTB tokeniser and METEOR are Java programs): "
            "install a Java runtime, e.g. `apt-get install default-jre-headless`, and put `java` on PATH"
        )
    try:
        from pycocoevalcap.bleu.bleu import Bleu
        from pycocoevalcap.cider.cider import Cider
        from pycocoevalcap.meteor.meteor import Meteor
        from pycocoevalcap.rouge.rouge import Rouge
        from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer
    except ImportError:
        raise OcctrainError(
            "caption metrics need pycocoevalcap: `pip install pycocoevalcap` (or `pip install -e '.[dev]'`)"
        ) from None
    ids = list(references)
    # One Java process for references and predictions alike: the tokeniser treats every
    # sentence on its own, and each start of Java costs a second or more.
    both = {("ref", i): [{"caption": r} for r in references[i]] for i in ids}
    both.update({("pred", i): [{"caption": predictions[i]}] for i in ids})
    with _java_stderr_kept_aside():
        tokenized = PTBTokenizer().tokenize(both)
    gts = {i: tokenized[("ref", i)] for i in ids}
    res = {i: tokenized[("pred", i)] for i in ids}
    scores: dict[str, float] = {}
    with contextlib.redirect_stdout(io.StringIO()):  # Bleu prints its length ratios
        bleu, _ = Bleu(4).compute_score(gts, res)
    scores.update({f"Bleu_{n + 1}": float(b) for n, b in enumerate(bleu)})
    scores["METEOR"] = float(_meteor(Meteor).compute_score(gts, res)[0])
    scores["ROUGE_L"] = float(Rouge().compute_score(gts, res)[0])
    scores["CIDEr"] = float(Cider().compute_score(gts, res)[0])
    return scores


class CaptionMetric(Metric):
    """BLEU-1..4, METEOR, ROUGE-L, CIDEr-D of generated text against references (pycocoevalcap).

    ``update(predictions, references, ids=None)``: one prediction string per sample and its
    references (a string or a list of strings). The strings travel across DDP processes
    as UTF-8 bytes in a uint8 tensor state; after gathering, samples repeated under the
    same id (a distributed sampler pads the last batch with repeats) count once.
    ``compute()`` returns pycocoevalcap's keys (fractions, as it returns them) and ``samples``.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    #: One uint8 tensor of encoded records per update; while synced, torchmetrics has
    #: concatenated the list into one tensor.
    text: list[Tensor] | Tensor

    def __init__(self, **kwargs: Any):
        super().__init__(**{"dist_sync_fn": _gather_bytes, **kwargs})
        self.add_state("text", [], dist_reduce_fx="cat")

    def update(
        self, predictions: Sequence[str], references: Sequence[str | Sequence[str]], ids: Sequence[Any] | None = None
    ) -> None:
        if len(predictions) != len(references) or (ids is not None and len(ids) != len(predictions)):
            raise ValueError(
                f"{len(predictions)} predictions, {len(references)} references and {len(ids) if ids else 0} ids differ "
                "in number"
            )
        records = []
        for k, (pred, refs) in enumerate(zip(predictions, references)):
            refs = [refs] if isinstance(refs, str) else list(refs)
            if not refs:
                raise ValueError(f"sample {k} has no reference text")
            records.append(json.dumps([None if ids is None else str(ids[k]), str(pred), [str(r) for r in refs]]))
        assert isinstance(self.text, list), "update() runs on the unsynced state"
        self.text.append(_encode(records).to(self.device))

    def samples(self) -> dict[str, tuple[str, list[str]]]:
        """The samples of every process, ``{id: (prediction, references)}``; unnamed ones get "#<position>" as id."""
        with self.sync_context(dist_sync_fn=self.dist_sync_fn):
            return self._local_samples()

    def _local_samples(self) -> dict[str, tuple[str, list[str]]]:
        out: dict[str, tuple[str, list[str]]] = {}
        if isinstance(self.text, list) and not self.text:
            return out
        for pos, record in enumerate(_decode(dim_zero_cat(self.text))):
            sid, pred, refs = json.loads(record)
            out.setdefault(f"#{pos}" if sid is None else sid, (pred, refs))
        return out

    def compute(self) -> dict[str, Any]:
        gathered = self._local_samples()  # compute() runs on synchronised states
        if not gathered:
            raise ValueError("CaptionMetric.compute() called before any update")
        values = self._scored_once(gathered) if self._is_synced else self._scores(gathered)
        out: dict[str, Any] = {k: v for k, v in zip(CAPTION_KEYS, values.cpu())}
        out["samples"] = torch.tensor(len(gathered))
        return out

    def _scores(self, gathered: dict[str, tuple[str, list[str]]]) -> Tensor:
        """pycocoevalcap's scores of ``gathered``, in ``CAPTION_KEYS`` order (float64)."""
        scores = coco_caption_scores({i: p for i, (p, _) in gathered.items()}, {i: r for i, (_, r) in gathered.items()})
        return torch.tensor([scores[k] for k in CAPTION_KEYS], dtype=torch.float64, device=self.device)

    def _scored_once(self, gathered: dict[str, tuple[str, list[str]]]) -> Tensor:
        """After a gather every process holds every sample: the first scores them and the
        others receive its scores. The scorers are Java programs (METEOR alone loads its
        paraphrase tables for seconds and takes a 2 GB heap), so N processes would pay that
        N times for the same numbers. A failure on the first is raised on every process
        (its own error there, a pointer to it elsewhere) rather than leaving them waiting."""
        import torch.distributed as dist

        first = 0 if self.process_group is None else dist.get_global_rank(self.process_group, 0)
        # The scores, then 1 if the first process computed them.
        values = torch.zeros(len(CAPTION_KEYS) + 1, dtype=torch.float64, device=self.device)
        error: Exception | None = None
        if dist.get_rank() == first:
            try:
                values[:-1] = self._scores(gathered)
                values[-1] = 1.0
            except Exception as exc:  # raised below, once the others know
                error = exc
        dist.broadcast(values, src=first, group=self.process_group)
        if error is not None:
            raise error
        if values[-1] != 1.0:
            raise OcctrainError("caption metrics failed on the first process; its error above says why")
        return values[:-1]
