"""``occtrain report RUN [RUN ...]``: the headline numbers of finished, scored runs as one
markdown page, each beside its baselines on the same samples, stamped with what produced it.

Every number comes from a stage's scores (``STAGE/eval/<split>/metrics.json``, written by
``occtrain eval``); the page names, per run, the recipe, the training seeds, the code
version that trained it and the code that scored it, the world (by name and content key)
and what of the split was scored (the metrics file's provenance: a subset is called one),
and the date. Runs scored on different world versions are refused; runs of different
worlds, subsets or code too, and a number set beside a baseline, a blanked twin or another
run's number scored on other items (each number's sample set, ``formats.metrics_file``),
unless ``--allow-mixed`` (the page then says what differs, at the number). With several
runs of one recipe (training seeds), a column gives the mean and the spread (min to max).
The docs' result pages are this command's output, never typed.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

from occtrain.data.blank_cameras import BLANK_SUFFIX
from occtrain.data.layout import SPLITS
from occtrain.errors import DataError
from occtrain.formats.metrics_file import Provenance, SampleSet, read_metrics

METRICS_FILE = "metrics.json"


@dataclass(frozen=True)
class Headline:
    """A kind of headline number: the metric keys it covers (a regular expression over a
    stage's score keys), what it is, and the baselines it is set beside (keys, where
    ``{0}``, ``{1}``... are the pattern's groups)."""

    pattern: str
    label: str
    digits: int = 1
    baselines: tuple[tuple[str, str], ...] = ()


HEADLINES = (
    Headline(
        r"occworld_(mIoU|IoU)",
        "reconstruction {0} (`occworld`)",
        1,
        (
            ("the per-voxel prior (no input)", "baseline_prior_occworld_{0}"),
            ("empty", "baseline_free_occworld_{0}"),
            ("the point budget's oracle", "baseline_budget_oracle_occworld_{0}"),
            ("ceiling: its cameras' pixels lifted at their true depth", "baseline_lifted_pixels_occworld_{0}"),
        ),
    ),
    Headline(
        r"occworld_movable_mIoU",
        "reconstruction movable-class mIoU (`occworld`)",
        2,
        (
            ("the per-voxel prior (no input)", "baseline_prior_occworld_movable_mIoU"),
            ("the point budget's oracle", "baseline_budget_oracle_occworld_movable_mIoU"),
            (
                "ceiling: its cameras' pixels lifted at their true depth",
                "baseline_lifted_pixels_occworld_movable_mIoU",
            ),
        ),
    ),
    Headline(r"occupied_share", "predicted occupied share (% of voxels)", 1, (("true", "true_occupied_share"),)),
    Headline(
        r"forecast_occworld_(mIoU|movable_mIoU)_(1s|2s|3s)",
        "forecast {0} at {1} (`occworld`)",
        2,
        (
            (
                "ceiling: the true future through the tokenizer",
                "baseline_true_future_reconstruction_forecast_occworld_{0}_{1}",
            ),
            (
                "ceiling: the moved present with the true agents pasted, through the tokenizer",
                "baseline_cv_moved_movers_reconstruction_forecast_occworld_{0}_{1}",
            ),
            (
                "the present moved at constant velocity, through the tokenizer",
                "baseline_cv_moved_reconstruction_forecast_occworld_{0}_{1}",
            ),
            ("Copy&Paste of the reconstruction", "baseline_copy_reconstruction_forecast_occworld_{0}_{1}"),
            ("the per-voxel prior (no input)", "baseline_prior_forecast_occworld_{0}_{1}"),
            ("copy the scene", "baseline_copy_forecast_occworld_{0}_{1}"),
            ("the scene moved at constant velocity", "baseline_cv_moved_forecast_occworld_{0}_{1}"),
        ),
    ),
    Headline(
        r"forecast_gain_over_moved_reconstruction_occworld_(mIoU|movable_mIoU)_(1s|2s|3s)",
        "forecast {0} at {1} minus the moved reconstruction's (points: what the model adds to its query)",
        2,
    ),
    Headline(
        r"forecast_share_of_reachable_gain_occworld_(mIoU|movable_mIoU)_(1s|2s|3s)",
        "forecast {0} at {1}: its gain over the moved reconstruction as a share of the true future's (%)",
        1,
    ),
    Headline(
        r"(?!\w*_(?:departing|turning|stopping)_)(plan(?:_\w+)?|head(?:_\w+)?|llm_action_tokens|anchor_\w+)_L2_stp3_avg",
        "plan `{0}`: L2 avg (`stp3`, m)",
        3,
        (
            ("constant acceleration along the route", "constant_acceleration_along_route_L2_stp3_avg"),
            ("constant acceleration along the route", "baseline_constant_acceleration_along_route_L2_stp3_avg"),
            ("constant acceleration", "baseline_constant_acceleration_L2_stp3_avg"),
            ("constant acceleration", "constant_acceleration_L2_stp3_avg"),
            ("constant velocity", "baseline_constant_velocity_L2_stp3_avg"),
            ("constant velocity", "constant_velocity_L2_stp3_avg"),
            ("standing still", "baseline_stationary_L2_stp3_avg"),
        ),
    ),
    *(
        Headline(
            rf"(plan(?:_\w+)?|head(?:_\w+)?|llm_action_tokens|anchor_\w+)_{subset}_L2_stp3_avg",
            f"plan `{{0}}` {where}: L2 avg (`stp3`, m)",
            3,
            tuple(
                (name, f"{key}_{subset}_L2_stp3_avg")
                for name, key in (
                    ("constant acceleration along the route", "constant_acceleration_along_route"),
                    ("constant acceleration along the route", "baseline_constant_acceleration_along_route"),
                    ("constant acceleration", "baseline_constant_acceleration"),
                    ("constant acceleration", "constant_acceleration"),
                    ("constant velocity", "baseline_constant_velocity"),
                    ("constant velocity", "constant_velocity"),
                    ("standing still", "baseline_stationary"),
                )
            ),
        )
        for subset, where in (
            ("departing", "where the truth departs from constant velocity (> 1 m at 3 s)"),
            ("turning", "where the route turns (the command)"),
            ("stopping", "where the truth stands still at 3 s"),
        )
    ),
    Headline(r"qa_overall", "NuScenes-QA accuracy (%)", 1, (("commonest per type", "baseline_prior_qa_overall"),)),
    Headline(
        r"meta_action_overall",
        "meta action right (%)",
        1,
        (
            ("commonest", "baseline_prior_meta_action_overall"),
            ("repeat the last past one", "baseline_repeat_last_meta_action_overall"),
        ),
    ),
    Headline(r"(\w*caption)_CIDEr", "`{0}` CIDEr", 3, (("the typical caption", "baseline_prior_{0}_CIDEr"),)),
)


#: The prefix of a stage's scores with its cameras blanked (``occtrain eval --blank-cameras``).
BLANKED = "blank_cameras/"
#: A forecast's score against the bar of copying its query: the present moved at constant
#: velocity through the tokenizer (what a model that writes its moved query back scores).
GAIN_OVER = "baseline_cv_moved_reconstruction_"
#: What a perfect forecast in the tokenizer's codes scores: the true future through it.
CEILING = "baseline_true_future_reconstruction_"


def check_split(split: str) -> None:
    """Refuse a ``--split`` that is not a split (``val``) or the folder an ``occtrain eval
    --data`` wrote and its split (``world_seed1-<key>/val``): a path that climbs out of the
    stage's ``eval/`` (``..``) or names anything else is one line."""
    parts = split.split("/")
    if len(parts) <= 2 and parts[-1] in SPLITS and all(p and p not in (".", "..") and "\\" not in p for p in parts):
        return
    raise DataError(
        f"--split {split}: a split ({', '.join(SPLITS)}), or the folder `occtrain eval --data` wrote under a stage's "
        "eval/ and its split (WORLD-KEY/val)"
    )


def same_items(provenance: Provenance | None, a: str, b: str) -> bool | None:
    """Whether keys ``a`` and ``b`` of one metrics file were scored on the same items (None:
    the file does not record it)."""
    first, second = _sample_set(provenance, a), _sample_set(provenance, b)
    if first is None or second is None:
        return None
    return first.digest == second.digest


def _sample_set(provenance: Provenance | None, key: str) -> SampleSet | None:
    return None if provenance is None else provenance.sample_set(key)


def with_gains(scores: dict[str, float], provenance: Provenance | None = None) -> dict[str, float]:
    """``scores`` and each forecast score's gain over the moved reconstruction on the same
    samples (``forecast_gain_over_moved_reconstruction_*``), overall and on the movable
    classes apart: the number a forecast that merely copies its query leaves at 0. No gain
    where the two were scored on other items (an eval merged over another's)."""
    gains = {
        key.replace("forecast_", "forecast_gain_over_moved_reconstruction_", 1): value - scores[GAIN_OVER + key]
        for key, value in scores.items()
        if key.startswith("forecast_occworld_")
        and GAIN_OVER + key in scores
        and same_items(provenance, key, GAIN_OVER + key) is not False
    }
    # What the model takes of what was there to take: the true future through the tokenizer
    # is what a perfect forecast in its codes scores.
    shares = {}
    for key, gain in gains.items():
        forecast = "forecast_" + key.removeprefix("forecast_gain_over_moved_reconstruction_")
        ceiling = scores.get(CEILING + forecast)
        reachable = None if ceiling is None else ceiling - scores[GAIN_OVER + forecast]
        if (
            reachable is not None
            and reachable > 0
            and same_items(provenance, forecast, CEILING + forecast) is not False
        ):
            shares[key.replace("gain_over_moved_reconstruction", "share_of_reachable_gain", 1)] = (
                100.0 * gain / reachable
            )
    return {**scores, **gains, **shares}


GAIN = "forecast_gain_over_moved_reconstruction_"


@dataclass(frozen=True)
class Run:
    """A run directory as the report reads it."""

    path: Path
    name: str
    stages: list[str]
    manifest: dict
    scores: dict[str, dict[str, float]]  # stage -> its scores on the split
    provenance: dict[str, Provenance | None]  # stage -> what they were measured on (None: not recorded)
    #: stage -> what its ``--blank-cameras`` twin was measured on, where it has one.
    blanked: dict[str, Provenance | None]

    @classmethod
    def read(cls, path: Path, split: str) -> Run:
        manifest_file = path / "manifest.json"
        if not manifest_file.is_file():
            raise DataError(f"{path}: not a run directory (no manifest.json); pass the --run-dir of an occtrain run")
        try:
            manifest = json.loads(manifest_file.read_text())
            stages = list(manifest.get("stages", {}))
        except (OSError, ValueError, AttributeError) as err:
            raise DataError(f"{path}: cannot read its manifest ({err}); rerun `occtrain run` on it") from None
        scores, provenance, blanked = {}, {}, {}
        for stage in stages:
            file = path / stage / "eval" / split / METRICS_FILE
            if file.is_file():
                measured = read_metrics(file)
                scores[stage] = with_gains(measured.metrics, measured.provenance)
                provenance[stage] = measured.provenance
                twin = path / stage / "eval" / (split + BLANK_SUFFIX) / METRICS_FILE
                if twin.is_file():  # ``occtrain eval --blank-cameras``: set beside each number
                    dark = read_metrics(twin)
                    blanked[stage] = dark.provenance
                    scores[stage].update({BLANKED + k: v for k, v in with_gains(dark.metrics, dark.provenance).items()})
        if not scores:
            raise DataError(f"{path}: no stage is scored on '{split}'; run `occtrain eval {path}/<stage>` first")
        return cls(path, str(manifest.get("name", path.name)), stages, manifest, scores, provenance, blanked)

    def items(self, stage: str, key: str) -> SampleSet | None:
        """The items ``key`` of ``stage`` was scored on (its blanked twin's for a ``BLANKED``
        key; a gain's are its forecast's); None where the metrics file does not record it."""
        if key.startswith(BLANKED):
            return self.blanked_items(stage, key.removeprefix(BLANKED))
        if key.startswith(GAIN):
            key = "forecast_" + key.removeprefix(GAIN)
        return _sample_set(self.provenance.get(stage), key)

    def blanked_items(self, stage: str, key: str) -> SampleSet | None:
        if key.startswith(GAIN):
            key = "forecast_" + key.removeprefix(GAIN)
        return _sample_set(self.blanked.get(stage), key)

    def _recorded(self) -> list[Provenance]:
        return [p for p in self.provenance.values() if p is not None]

    def worlds(self) -> set[str]:
        """The worlds its stages were scored on, by name and content key."""
        return {f"{p.world_name} [{p.world}]" for p in self._recorded()} or {"unrecorded"}

    def world_versions(self) -> set[str]:
        return {p.world_version or "unrecorded" for p in self._recorded()} or {"unrecorded"}

    def coverage(self) -> str:
        """What its stages were scored on: the whole split, or each subset (and where the
        items of each number are not recorded, that they are not)."""
        said = {
            stage: "provenance not recorded"
            if p is None
            else p.describe() + ("" if p.sample_sets else " (the items of each number not recorded)")
            for stage, p in self.provenance.items()
        }
        if len(set(said.values())) == 1:
            return next(iter(said.values()))
        return "; ".join(f"{stage}: {what}" for stage, what in said.items())

    def code(self) -> str:
        """The code that trained its stages, and, where another, the code that scored them."""
        entries = self.manifest.get("stages", {}).values()
        trained = sorted({e.get("code_version") or "?" for e in entries})
        scored = sorted({p.code_version or "?" for p in self._recorded()} - set(trained))
        return ", ".join(trained) + (f"; scored by {', '.join(scored)}" if scored else "")

    def stamp(self) -> str:
        """The run as a page names it: recipe, training seed, code and world, never its path."""
        entries = self.manifest.get("stages", {}).values()
        seeds = sorted({str((e.get("config") or {}).get("trainer", {}).get("seed", "?")) for e in entries})
        scored = max((self.path / s / "eval").stat().st_mtime for s in self.scores)
        return (
            f"recipe {self.name}, training seed {', '.join(seeds)}, code {self.code()}, "
            f"world {'; '.join(sorted(self.worlds()))}, scored {time.strftime('%Y-%m-%d', time.gmtime(scored))} "
            f"on {self.coverage()}"
        )


def mixed(runs: list[Run]) -> list[str]:
    """What differs between runs a table would set side by side: the world, what of the
    split was scored, the code that trained or scored them, and any number set beside a
    baseline, its blanked twin or another run's that was scored on other items. Empty when
    nothing does."""
    found = []
    for what, of in (
        ("world", lambda run: "; ".join(sorted(run.worlds()))),
        ("what was scored", Run.coverage),
        ("code", Run.code),
    ):
        values = [of(run) for run in runs]
        if len(set(values)) > 1:
            found.append(f"the runs differ in {what} ({'; '.join(f'run {i}: {v}' for i, v in enumerate(values))})")
    return found + other_items(runs)


def other_items(runs: list[Run]) -> list[str]:
    """Each table cell whose number and what it is set beside were scored on other items:
    ``stage key (its items) beside name (their items)``. Numbers of a file that does not
    record its items are not compared (its stamp says so)."""
    found = []
    for stage, _, _, key, bases in _rows(runs):
        for i, run in enumerate(runs):
            mine = run.items(stage, key)
            if mine is None:
                continue
            for name, base in bases:
                theirs = run.items(stage, base)
                if base in run.scores.get(stage, {}) and theirs is not None and theirs.digest != mine.digest:
                    found.append(
                        f"run {i}'s {stage} {key} ({mine.describe()}) would stand beside {name} scored on other "
                        f"items ({theirs.describe()})"
                    )
        digests = {items.digest for run in runs if (items := run.items(stage, key)) is not None}
        if len(digests) > 1:
            found.append(f"{stage} {key} was scored on other items in each run")
    return list(dict.fromkeys(found))


def _words(group: str) -> str:
    """A key's part as a reader writes it: ``movable_mIoU`` -> movable-class mIoU, ``1s`` -> 1 s."""
    return {"movable_mIoU": "movable-class mIoU", "1s": "1 s", "2s": "2 s", "3s": "3 s"}.get(group, group)


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _rows(runs: list[Run]) -> list[tuple[str, str, int, str, list[tuple[str, str]]]]:
    """(stage, label, digits, score key, baselines) of every headline some run has."""
    stages = list(dict.fromkeys(s for run in runs for s in run.stages))
    rows = []
    for stage in stages:
        keys = list(dict.fromkeys(k for run in runs for k in run.scores.get(stage, {})))
        blanked = any(k.startswith(BLANKED) for k in keys)
        for headline in HEADLINES:
            for key in keys:
                match = re.fullmatch(headline.pattern, key)
                if match is None:
                    continue
                groups = match.groups()
                bases = [(label, b.format(*groups)) for label, b in headline.baselines]
                if blanked:
                    bases.insert(0, ("the same with its cameras blanked", BLANKED + key))
                label = headline.label.format(*(_words(g) for g in groups))
                rows.append((stage, label, headline.digits, key, bases))
    return rows


def command_line(runs: int, split: str = "val", title: str = "", allow_mixed: bool = False) -> str:
    """The ``occtrain report`` command a page says wrote it, naming its runs by their place
    in the page's list (``RUN_0`` ...), never by where they lay on the machine that made it."""
    split_flag = ["--split", split] if split != "val" else []
    title_flag = ["--title", f"'{title}'"] if title else []
    mixed_flag = ["--allow-mixed"] if allow_mixed else []
    return " ".join(["occtrain report", *(f"RUN_{i}" for i in range(runs)), *split_flag, *title_flag, *mixed_flag])


def report(
    runs: list[Run], split: str = "val", command: str = "occtrain report", title: str = "", allow_mixed: bool = False
) -> str:
    """The markdown page (see the module docstring), under ``# title`` when given. Runs of
    different worlds, subsets or code are refused unless ``allow_mixed``; then the page says
    what differs."""
    versions = [run.world_versions() for run in runs]
    if len(set().union(*versions)) > 1:
        raise DataError(
            "the runs were scored on different world versions ("
            + "; ".join(f"{run.path}: {', '.join(sorted(v))}" for run, v in zip(runs, versions))
            + "); report each world on its own"
        )
    differ = mixed(runs)
    if differ and not allow_mixed:
        more = f" (and {len(differ) - 1} more)" if len(differ) > 1 else ""
        raise DataError(
            f"{differ[0]}{more}; score them alike (the same --tasks and --samples of occtrain eval, by one checkout) "
            "or report them apart, or pass --allow-mixed to set them side by side anyway"
        )
    seeds_of_one_recipe = len(runs) > 1 and len({run.name for run in runs}) == 1
    head = [f"run {i}" for i in range(len(runs))]
    scored = runs[0].coverage() if not differ else "what each run states below"
    lines = [
        *([f"# {title}", ""] if title else []),
        f"World {', '.join(sorted(versions[0]))}; scored on {scored} (`occtrain eval`). Generated by `{command}` from:",
        "",
        *(f"- run {i}: {run.stamp()}" for i, run in enumerate(runs)),
        *(["", f"**Mixed on purpose (`--allow-mixed`)**: {'; '.join(differ)}."] if differ else []),
        "",
        f"| stage | metric | {' / '.join(head)} |{' mean (min to max) |' if seeds_of_one_recipe else ''} baselines "
        "(on the same samples; per run where they differ) |",
        f"|---|---|---|{'---|' if seeds_of_one_recipe else ''}---|",
    ]
    for stage, label, digits, row_key, bases in _rows(runs):
        values = [run.scores.get(stage, {}).get(row_key) for run in runs]
        have = [v for v in values if v is not None]
        cells = [stage, label, " / ".join(_fmt(v, digits) for v in values)]
        if seeds_of_one_recipe:
            mean = sum(have) / len(have)
            cells.append(f"{_fmt(mean, digits)} ({_fmt(min(have), digits)} to {_fmt(max(have), digits)})")
        cells.append(_baselines_cell(runs, stage, row_key, bases, digits))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n" + _wall_times(runs)


def _baselines_cell(runs: list[Run], stage: str, row_key: str, bases: list[tuple[str, str]], digits: int) -> str:
    """The baselines a row's number stands beside, each run's own where they differ, and a
    baseline scored on other items than the number said so (``--allow-mixed`` lets it in)."""
    seen: set[str] = set()
    shown = []
    for name, key in bases:
        per_run = [run.scores.get(stage, {}).get(key) for run in runs]
        if name in seen or all(v is None for v in per_run):
            continue
        seen.add(name)
        # Each run's own where they differ (another tokenizer copies another reconstruction).
        texts = [_fmt(v, digits) for v in per_run]
        other = sorted(
            {
                theirs.describe()
                for run in runs
                if (theirs := run.items(stage, key)) is not None
                and (mine := run.items(stage, row_key)) is not None
                and theirs.digest != mine.digest
            }
        )
        warn = f" (on other items: {', '.join(other)})" if other else ""
        shown.append(f"{name} {texts[0] if len(set(texts)) == 1 else ' / '.join(texts)}{warn}")
    return "; ".join(shown) or "-"


def _wall_times(runs: list[Run]) -> str:
    """Each stage's training wall time per run (the manifest's sum over attempts; the world's
    synthesis and shards come before the first stage and are not counted)."""
    stages = list(dict.fromkeys(s for run in runs for s in run.stages))
    lines = ["", f"| stage | training wall time, s: {' / '.join(f'run {i}' for i in range(len(runs)))} |", "|---|---|"]
    totals = [0.0] * len(runs)
    for stage in stages:
        times = [run.manifest["stages"].get(stage, {}).get("wall_time_s") for run in runs]
        for i, t in enumerate(times):
            totals[i] += t if isinstance(t, (int, float)) else 0.0
        lines.append(f"| {stage} | {' / '.join('-' if t is None else f'{t:.0f}' for t in times)} |")
    lines.append(f"| all stages | {' / '.join(f'{t:.0f}' for t in totals)} |")
    return "\n".join(lines) + "\n"
