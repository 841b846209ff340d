"""What a command-line run reconstructs with, kept beside its outputs (``DIR/run.json``).

A rerun on the same ``--out`` resumes: the tracks already finished are not redone. So a rerun
with another method, other bounds or other filters would mix two runs' tracks in one output
without a word; it is refused instead, naming what differs. ``trajrecon plot`` reads the file to
draw with the settings the stored tracks were made with.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from .config import FILTER_GATE_SIGMA, ReconstructionConfig, check_filter_gate
from .inputs import Bounds, InputError

RUN_FILE = "run.json"


@dataclass(frozen=True)
class RunSettings:
    """The settings every track of a run shares (``filters`` as a set: their order changes
    no output); ``sample_step_s``: the regular samples kept (``samples.parquet``), none when
    None; the sliding windows' ``window_plots``, ``trial_step_s`` and ``criterion`` (the
    defaults of :class:`solver.config.ReconstructionConfig`; the refined method does not use
    them); ``filter_gate_sigma``: the filters' validation gate (sigmas; None: no gate,
    :mod:`solver.estimation.gating`); ``editions``: the ASTERIX editions chosen per category
    other than the decoder's defaults, as ``((21, "0.26"), ...)`` (sorted, defaults left out:
    a run that names the default edition is the default run;
    :data:`solver.io.asterix.EDITIONS`), in ``run.json`` as ``{"21": "0.26"}``: a rerun
    reading the recording as another edition is another run; ``date``: the UTC date given for
    the recording's times of day (``YYYY-MM-DD``, :mod:`solver.io.dates`; None: its own, if
    any): a rerun with another date would mix two days' ``time_utc``."""

    method: str = "refined"
    bounds: Bounds = field(default_factory=Bounds)
    filters: tuple[str, ...] = ()
    sample_step_s: float | None = None
    window_plots: int = ReconstructionConfig.window_plots
    trial_step_s: float = ReconstructionConfig.trial_step_s
    criterion: str = ReconstructionConfig.criterion
    filter_gate_sigma: float | None = FILTER_GATE_SIGMA
    editions: tuple[tuple[int, str], ...] = ()
    date: str | None = None

    def __post_init__(self) -> None:
        if self.date is not None:
            from .io.dates import parse_date

            object.__setattr__(self, "date", parse_date(self.date))
        try:
            check_filter_gate(self.filter_gate_sigma)
        except ValueError as e:
            raise InputError(("filter_gate_sigma",), str(e)) from None
        if self.editions:
            object.__setattr__(self, "editions", _chosen_editions(self.editions))

    def asterix_editions(self) -> dict[int, Any] | None:
        """The decoder's ``editions=`` (None: the defaults)."""
        if not self.editions:
            return None
        from .io.asterix import editions_named

        return editions_named(dict(self.editions))

    def config(self) -> ReconstructionConfig:
        more = {} if self.sample_step_s is None else {"sample_step_s": self.sample_step_s}
        return ReconstructionConfig(method=self.method, bounds=self.bounds,  # type: ignore[arg-type]
                                    window_plots=self.window_plots,
                                    trial_step_s=self.trial_step_s,
                                    criterion=self.criterion, **more)  # type: ignore[arg-type]

    def as_json(self) -> dict[str, Any]:
        return {"method": self.method, "filters": list(dict.fromkeys(self.filters)),
                "bounds": {k: list(getattr(self.bounds, k)) for k in ("u", "w", "v")},
                "sample_step_s": self.sample_step_s,
                "window": {"plots": self.window_plots, "trial_step_s": self.trial_step_s},
                "criterion": self.criterion, "filter_gate_sigma": self.filter_gate_sigma,
                "editions": {str(cat): name for cat, name in self.editions},
                "date": self.date}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> RunSettings:
        """A run's settings (those a file written before a field existed lacks: the
        defaults, which such a run used)."""
        b = doc.get("bounds") or {}
        w = doc.get("window") or {}
        defaults = Bounds()
        gate = doc.get("filter_gate_sigma", FILTER_GATE_SIGMA)
        return cls(str(doc.get("method", "refined")),
                   Bounds(**{k: tuple(float(x) for x in b.get(k, getattr(defaults, k)))
                             for k in ("u", "w", "v")}),
                   tuple(doc.get("filters") or ()),
                   None if doc.get("sample_step_s") is None else float(doc["sample_step_s"]),
                   int(w.get("plots", cls.window_plots)),
                   float(w.get("trial_step_s", cls.trial_step_s)),
                   str(doc.get("criterion", cls.criterion)),
                   None if gate is None else float(gate),
                   tuple((int(k), str(v)) for k, v in (doc.get("editions") or {}).items()),
                   None if doc.get("date") is None else str(doc["date"]))


def _chosen_editions(editions: Sequence[tuple[int, str]]) -> tuple[tuple[int, str], ...]:
    """``editions`` checked against libasterix's (:class:`InputError` at ``editions``, listing
    the choices; a category named twice too), sorted, the defaults left out."""
    from .io.asterix import DEFAULT_EDITIONS, EDITIONS, parse_edition

    chosen: dict[int, str] = {}
    for cat, name in editions:
        try:
            cat, name = parse_edition(f"{cat}={name}")
        except ValueError as e:
            raise InputError(("editions",), str(e)) from None
        if chosen.get(cat, name) != name:
            raise InputError(("editions",), f"CAT{cat:03d} is given two editions, "
                             f"{chosen[cat]} and {name}: give one")
        chosen[cat] = name
    return tuple((cat, name) for cat, name in sorted(chosen.items())
                 if EDITIONS[cat][name] is not DEFAULT_EDITIONS[cat])


def parse_bounds(items: Sequence[str]) -> Bounds:
    """``["v=15,250", "u=-10,10"]`` -> :class:`Bounds` (the others at their defaults),
    validated; :class:`InputError` at ``bounds`` / ``bounds.<name>``."""
    values: dict[str, tuple[float, float]] = {}
    for item in items:
        name, _, pair = item.partition("=")
        name = name.strip()
        if name not in ("u", "w", "v"):
            raise InputError(("bounds",), f"{item!r}: name u, w or v (e.g. v=15,250)")
        try:
            lo, hi = (float(x) for x in pair.split(","))
        except ValueError:
            raise InputError(("bounds", name), f"{item!r}: give MIN,MAX (e.g. {name}="
                             f"{','.join(f'{x:g}' for x in getattr(Bounds(), name))})"
                             ) from None
        values[name] = (lo, hi)
    bounds = Bounds(**values)
    bounds.validate()
    return bounds


def finished_any(out: Path) -> bool:
    """Whether ``out`` holds a finished track (a line of its ledger): a run that stopped
    before any (a bad recording, a stop during the start) leaves nothing to resume, and its
    ``run.json`` and ``inputs.json`` are replaced by the next run's (they refused the
    corrected command; a docs-following helper)."""
    from .batch import ledger_entries

    return bool(ledger_entries(out))


def stored(out: Path) -> RunSettings | None:
    """The settings of the run in ``out``, or None (no run there, or one written before this
    file was kept)."""
    path = out / RUN_FILE
    if not path.is_file():
        return None
    try:
        return RunSettings.from_json(json.loads(path.read_text(encoding="utf-8")))
    except (ValueError, TypeError, AttributeError) as e:
        raise InputError(("out",), f"{path} is not a run's settings ({e}); remove it or "
                         "choose another --out") from None


def keep(out: Path, settings: RunSettings) -> None:
    """Record ``settings`` in ``out`` (before any track is solved); :class:`InputError` when
    ``out`` holds finished tracks of a run with other settings."""
    earlier = stored(out)
    if earlier is not None:
        old, new = earlier.as_json(), settings.as_json()
        same = {"filters": lambda a, b: sorted(a) == sorted(b)}
        differ = [f"{k} {old[k]} (asked: {new[k]})" for k in old
                  if not same.get(k, lambda a, b: a == b)(old[k], new[k])]
        if not differ:
            return
        if finished_any(out):
            raise InputError(("out",), f"{out} holds a run made with {'; '.join(differ)}. A "
                             "rerun resumes that run, so it takes the same settings: give "
                             "them, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{RUN_FILE}.tmp"
    tmp.write_text(json.dumps(settings.as_json(), indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, out / RUN_FILE)


INPUTS_FILE = "inputs.json"
FINGERPRINT_BYTES = 1 << 20


def fingerprint(path: Path) -> dict[str, Any]:
    """A file's name, size and SHA-256 of its first and last MiB (a whole recording of GBs is
    not read twice for this)."""
    size = path.stat().st_size
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        digest.update(f.read(FINGERPRINT_BYTES))
        if size > FINGERPRINT_BYTES:
            f.seek(max(size - FINGERPRINT_BYTES, FINGERPRINT_BYTES))
            digest.update(f.read())
    return {"name": path.name, "bytes": size, "sha256_ends": digest.hexdigest()}


_WHAT = {"recording": "the recording", "sensors": "the sensor file",
         "software": "the software (version and solver sources)"}


@cache
def software() -> dict[str, str]:
    """This software's version and the SHA-256 of the solver's sources (every ``.py`` and
    ``.sh`` under ``solver/``, by relative path): what made a run's tracks. A rerun after an
    upgrade resumed the run and mixed two versions' tracks without a word (up to 8.7 m and
    0.7 m/s apart; a walkthrough helper)."""
    try:
        version = importlib.metadata.version("radar-trajrecon")
    except importlib.metadata.PackageNotFoundError:
        version = "0+unknown"
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".sh")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return {"version": version, "solver_sha256": digest.hexdigest()}


def keep_inputs(out: Path, recording: Path, sensors: Path) -> None:
    """Record which recording and sensor file ``out``'s run reads, and which software
    (:func:`software`) reads them (``DIR/inputs.json``); :class:`InputError` when ``out`` holds
    a run of other inputs (its finished tracks would be kept as the new recording's: they
    were, silently, when only the settings were compared; found by a fuzz helper) or made by
    other software (its tracks and the new ones would differ)."""
    if not (recording.is_file() and sensors.is_file()):
        return  # the readers say what is wrong with them
    now = {"recording": fingerprint(recording), "sensors": fingerprint(sensors),
           "software": software()}
    path = out / INPUTS_FILE
    if path.is_file():
        try:
            before = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            before = None
        differ = [k for k in now if not isinstance(before, dict) or before.get(k) != now[k]]
        if not differ:
            return
        if finished_any(out):
            what = " and ".join(_WHAT[k] for k in differ)
            verb = "differ" if len(differ) > 1 else "differs"
            raise InputError(("out",), f"{out} holds a run made from other inputs ({what} "
                             f"{verb} from {path.name}'s): a rerun resumes that run, so it "
                             "takes the same files; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{INPUTS_FILE}.tmp"
    tmp.write_text(json.dumps(now, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)
