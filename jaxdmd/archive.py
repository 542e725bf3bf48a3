"""The island archive: experience management with island-based evolution (paper, Sec. III.D).

The archive keeps every fitted skeleton worth remembering, spread over ``m`` islands that evolve
independently, and draws the in-context examples of the next prompt from one of them. It follows
FunSearch's ``programs_database.py`` (islands, clusters of equal score, softmax sampling, periodic
reset of the weaker half of the islands), rewritten as immutable values and pure functions:

- ``Entry``, ``Island``, ``ArchiveConfig`` and ``Archive`` are frozen dataclasses, registered as
  *static* pytrees (no array leaves; a ``SearchState`` may hold an ``Archive`` and still be
  ``jax.tree.map``-ed or passed through ``eqx.filter_jit``). They are hashable and compared by
  value. Every function returns a new archive and leaves its argument untouched.
- All randomness comes from a JAX PRNG key passed in; results are deterministic given the key.
- ``to_dict`` / ``from_dict`` give a JSON-serialisable form for resumable runs.

Scores
    ``score`` is ``-mean NMSE`` over the state equations (higher is better, at most 0). Dropped
    candidates carry ``-inf`` (or NaN); ``register`` ignores them, so a whole round can be passed
    through without filtering. Positive scores are rejected: they mean a different score was used.

Clusters (derived, not stored)
    An island stores a flat tuple of entries; its clusters are computed when needed. Two entries
    of an island share a cluster when their errors agree on a log scale::

        key(e) = round(log10(max(-e.score, nmse_floor)) / cluster_precision)

    ``cluster_precision`` is in decades (default 0.01, i.e. relative errors within ~2.3 %), so that
    "similar score" means "similar *relative* error" whether the errors are near 1 or near 1e-6.
    Errors below ``nmse_floor`` (default 1e-12, float64 round-off of a perfect fit) are all one.

Normalisation (before every softmax, so a temperature means the same on every data set)
    Cluster:  ``phi(C) = -log10(max(-mean score of C, nmse_floor))`` (orders of magnitude of
              accuracy), min-max normalised over the clusters of the island to [0, 1];
              ``P(C) = softmax(phi_norm / tau_c)``. The log scale matches the clustering and keeps
              1e-4 and 1e-3 apart even when a 1.5 outlier is on the island (a linear min-max would
              squash them together). Consequences: sampling is invariant to multiplying all scores
              by a positive factor (and to powers of the NMSE); ``tau_c`` is the temperature on a
              scale where the island's worst cluster is 0 and its best is 1.
    Skeleton: ``l_norm = (l - min l) / (max l - min l)`` over the entries of the chosen cluster
              (code length in AST nodes); ``P(h) = softmax(-l_norm / tau_l)``.
    A constant feature (one cluster, equal lengths) normalises to 0, i.e. a uniform choice.

Sampling (``sample_examples``)
    1) an island uniformly (unless given); 2) ``examples_per_prompt`` *distinct* entries, each by
    drawing a cluster and then a skeleton within it as above, without replacement (exhausted
    clusters drop out); fewer if the island holds fewer entries. The examples are returned ordered
    worst to best, so the prompt ends with its best example, as in FunSearch.

Capacity
    An island keeps at most ``max_entries_per_island`` entries; beyond that the worst ones (lowest
    score, then longest, then oldest) are dropped. Identical sources within an island are merged,
    keeping the better score.

Reset (``reset_weak_islands`` / ``maybe_reset``)
    As FunSearch: the ``n_islands // 2`` islands with the lowest best score (ties broken at random)
    are emptied and each re-seeded with the best entry of a surviving island chosen uniformly at
    random. ``maybe_reset`` does so every ``reset_period`` rounds (0 = never).

Per-equation recombination (beyond the paper)
    The losses are separable by state equation, so the best line for each equation can sit in
    different skeletons. ``best_lines`` finds, for every equation ``j``, the entry with the lowest
    ``losses[j]`` over all islands; ``recombine`` turns that into a short list of ``Recombination``
    plans (which entry supplies which equation, and the loss expected before refitting). Plans are
    data only: the search engine owns splicing the source lines and refitting the result.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from jaxdmd.ties import settled

__all__ = [
    "Archive",
    "ArchiveConfig",
    "Cluster",
    "Entry",
    "Island",
    "Recombination",
    "best",
    "best_lines",
    "best_per_island",
    "clusters",
    "diverse_parents",
    "from_dict",
    "maybe_reset",
    "new_archive",
    "recombine",
    "register",
    "register_many",
    "reset_weak_islands",
    "sample_examples",
    "to_dict",
    "top_entries",
]

FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------


def _floats(values: Iterable[Any], name: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in np.asarray(values, dtype=np.float64).ravel())
    except (TypeError, ValueError) as err:
        raise TypeError(f"Entry.{name} must be a sequence of numbers, got {values!r}") from err


def _freeze_requests(requests: Any) -> tuple[dict, ...]:
    if isinstance(requests, Mapping):
        requests = (requests,)
    try:
        # A JSON round trip both checks that the requests can be saved and decouples the entry
        # from the caller's (mutable) dictionaries.
        return tuple(json.loads(json.dumps(dict(r))) for r in requests)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"Entry.requests must be a sequence of JSON-serialisable dicts, got {requests!r}"
        ) from err


@dataclass(frozen=True)
class Entry:
    """One fitted skeleton, as the archive remembers it.

    Attributes:
        source: the normalised skeleton source (the identity of the entry within an island).
        score: ``-mean NMSE`` over the equations; higher is better, at most 0, ``-inf`` if dropped.
        losses: the NMSE of each output equation (same order as the task's outputs).
        params: the fitted parameter vector.
        length: the code length (AST node count) used for the length softmax.
        round: the round the entry was registered in.
        requests: the variable requests (JSON dicts) written with the skeleton.
    """

    source: str
    score: float
    losses: tuple[float, ...]
    params: tuple[float, ...]
    length: int
    round: int
    requests: tuple[dict, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.source, str):
            raise TypeError(f"Entry.source must be a str, got {type(self.source).__name__}")
        score = float(self.score)
        if score > 0:
            raise ValueError(
                f"Entry.score must be -NMSE (<= 0, higher is better), got {score}; "
                "pass the negated mean NMSE."
            )
        if int(self.length) < 0:
            raise ValueError(f"Entry.length must be >= 0, got {self.length}")
        object.__setattr__(self, "score", score)
        object.__setattr__(self, "losses", _floats(self.losses, "losses"))
        object.__setattr__(self, "params", _floats(self.params, "params"))
        object.__setattr__(self, "length", int(self.length))
        object.__setattr__(self, "round", int(self.round))
        object.__setattr__(self, "requests", _freeze_requests(self.requests))

    def __hash__(self) -> int:
        requests = json.dumps(self.requests, sort_keys=True)
        return hash(
            (self.source, self.score, self.losses, self.params, self.length, self.round, requests)
        )

    @property
    def is_valid(self) -> bool:
        """Whether the archive accepts this entry (its score is finite)."""
        return math.isfinite(self.score)


@dataclass(frozen=True)
class Island:
    """A sub-population: a flat tuple of entries with distinct sources.

    Clusters are derived from the scores when needed (see ``clusters``), not stored.
    """

    entries: tuple[Entry, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "entries", tuple(self.entries))


@dataclass(frozen=True)
class ArchiveConfig:
    """Hyper-parameters of the archive (paper: m = 10, tau_c = tau_l = 0.2).

    Attributes:
        n_islands: number of islands ``m``.
        tau_c: temperature of the cluster softmax (on normalised log accuracy, see module doc).
        tau_l: temperature of the skeleton softmax (on normalised code length).
        examples_per_prompt: number of distinct in-context examples drawn per prompt.
        reset_period: reset the weaker half of the islands every this many rounds; 0 = never.
        max_entries_per_island: capacity of an island; the worst entries are dropped beyond it.
        cluster_precision: width of a score cluster in decades of NMSE.
        nmse_floor: errors below this are treated as equal (exact fits).
    """

    n_islands: int = 10
    tau_c: float = 0.2
    tau_l: float = 0.2
    examples_per_prompt: int = 2
    reset_period: int = 4
    max_entries_per_island: int = 200
    cluster_precision: float = 0.01
    nmse_floor: float = 1e-12

    def __post_init__(self) -> None:
        checks = [
            (self.n_islands >= 1, "n_islands must be >= 1"),
            (self.tau_c > 0, "tau_c must be > 0"),
            (self.tau_l > 0, "tau_l must be > 0"),
            (self.examples_per_prompt >= 1, "examples_per_prompt must be >= 1"),
            (self.reset_period >= 0, "reset_period must be >= 0 (0 = never)"),
            (self.max_entries_per_island >= 1, "max_entries_per_island must be >= 1"),
            (self.cluster_precision > 0, "cluster_precision must be > 0 (decades)"),
            (self.nmse_floor > 0, "nmse_floor must be > 0"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"ArchiveConfig: {message}; got {self}")


@dataclass(frozen=True)
class Archive:
    """The islands and the configuration they are sampled with."""

    islands: tuple[Island, ...]
    config: ArchiveConfig = ArchiveConfig()

    def __post_init__(self) -> None:
        object.__setattr__(self, "islands", tuple(self.islands))
        if len(self.islands) != self.config.n_islands:
            raise ValueError(
                f"Archive has {len(self.islands)} islands but config.n_islands = "
                f"{self.config.n_islands}"
            )

    @property
    def size(self) -> int:
        """Total number of entries over all islands."""
        return sum(len(island.entries) for island in self.islands)


@dataclass(frozen=True)
class Cluster:
    """Entries of one island whose errors agree to ``cluster_precision`` decades."""

    key: int
    score: float  # mean score of the members
    entries: tuple[Entry, ...]


@dataclass(frozen=True)
class Recombination:
    """A plan for a recombined candidate: equation ``j`` is taken from ``donors[j]``.

    ``losses[j] = donors[j].losses[j]`` is the loss expected before refitting; ``score`` the
    matching expected score. The search engine splices the lines and refits.
    """

    donors: tuple[Entry, ...]
    losses: tuple[float, ...]

    @property
    def score(self) -> float:
        return -float(np.mean(self.losses))


for _cls in (Entry, Island, ArchiveConfig, Archive, Cluster, Recombination):
    jax.tree_util.register_static(_cls)


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _better_key(entry: Entry) -> tuple[float, int, int]:
    """Sort key, larger is better: higher score, then shorter, then older (scores equal to
    :data:`jaxdmd.ties.SIGNIFICANT` digits are a tie: the last bits do not rank)."""
    return (settled(entry.score), -entry.length, -entry.round)


def _log_error(score: float, floor: float) -> float:
    return math.log10(max(-score, floor))


def _check_island(archive: Archive, island: int) -> int:
    n = len(archive.islands)
    if not (isinstance(island, int | np.integer) and -n <= island < n):
        raise IndexError(f"island must be an int in [0, {n}), got {island!r}")
    return int(island) % n


def _uniforms(key: jax.Array, n: int) -> np.ndarray:
    """``n`` uniforms in [0, 1) from ``key`` (one device call per sampling function)."""
    return np.asarray(jax.random.uniform(key, (n,)), dtype=np.float64)


def _choose(logits: np.ndarray, u: float) -> int:
    """Inverse-CDF draw from ``softmax(logits)``; ``-inf`` logits are never drawn."""
    logits = np.asarray(logits, dtype=np.float64)
    p = np.exp(logits - np.max(logits))
    cdf = np.cumsum(p)
    index = int(np.searchsorted(cdf, u * cdf[-1], side="right"))
    index = min(index, len(p) - 1)
    while p[index] == 0.0:  # u * cdf[-1] rounding onto a masked tail
        index -= 1
    return index


def _minmax(x: np.ndarray) -> np.ndarray:
    span = np.max(x) - np.min(x)
    if not span > 0:
        return np.zeros_like(x)
    return (x - np.min(x)) / span


def _with_entries(island: Island, entries: Iterable[Entry], config: ArchiveConfig) -> Island:
    entries = tuple(entries)
    if len(entries) > config.max_entries_per_island:
        keep = sorted(range(len(entries)), key=lambda i: _better_key(entries[i]), reverse=True)
        keep = sorted(keep[: config.max_entries_per_island])  # preserve insertion order
        entries = tuple(entries[i] for i in keep)
    return Island(entries)


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------


def new_archive(seed: Entry, config: ArchiveConfig | None = None) -> Archive:
    """An archive whose every island holds only ``seed`` (the linear seed skeleton)."""
    config = ArchiveConfig() if config is None else config
    if not seed.is_valid:
        raise ValueError(
            f"the seed skeleton must have a finite score, got {seed.score}; check that the "
            "linear seed fits the data"
        )
    return Archive(tuple(Island((seed,)) for _ in range(config.n_islands)), config)


def register(archive: Archive, entry: Entry, island: int | None) -> Archive:
    """``archive`` with ``entry`` added to ``island`` (all islands if ``None``).

    Entries with a non-finite score (dropped candidates) are ignored: the archive is returned
    unchanged. An entry whose source is already on the island replaces it only if it scores
    strictly better. The island is then trimmed to ``max_entries_per_island``.
    """
    if not entry.is_valid:
        return archive
    n = len(archive.islands)
    targets = range(n) if island is None else (_check_island(archive, island),)
    islands = list(archive.islands)
    for k in targets:
        entries = list(islands[k].entries)
        same = [i for i, e in enumerate(entries) if e.source == entry.source]
        if same:
            i = same[0]
            if settled(entry.score) > settled(entries[i].score):
                entries[i] = entry
            else:
                continue
        else:
            entries.append(entry)
        islands[k] = _with_entries(islands[k], entries, archive.config)
    return dataclasses.replace(archive, islands=tuple(islands))


def register_many(
    archive: Archive, entries: Iterable[Entry], islands: int | Sequence[int | None] | None
) -> Archive:
    """Register several entries: all into ``islands`` (an index, or ``None`` for every island),
    or ``entries[i]`` into ``islands[i]``."""
    entries = tuple(entries)
    if islands is None or isinstance(islands, int | np.integer):
        islands = (islands,) * len(entries)
    if len(islands) != len(entries):
        raise ValueError(f"got {len(entries)} entries but {len(islands)} island indices")
    for entry, island in zip(entries, islands, strict=True):
        archive = register(archive, entry, island)
    return archive


# --------------------------------------------------------------------------------------------
# Queries
# --------------------------------------------------------------------------------------------


def clusters(island: Island, config: ArchiveConfig) -> tuple[Cluster, ...]:
    """The clusters of ``island``, from worst to best (see the module doc for the key)."""
    groups: dict[int, list[Entry]] = {}
    for entry in island.entries:
        key = round(_log_error(entry.score, config.nmse_floor) / config.cluster_precision)
        groups.setdefault(-key, []).append(entry)  # -key: larger is better
    return tuple(
        Cluster(key=-k, score=float(np.mean([e.score for e in g])), entries=tuple(g))
        for k, g in sorted(groups.items())
    )


def best_per_island(archive: Archive) -> tuple[Entry | None, ...]:
    """The best entry of each island (``None`` for an empty island)."""
    return tuple(
        max(island.entries, key=_better_key) if island.entries else None
        for island in archive.islands
    )


def best(archive: Archive) -> Entry:
    """The best entry over all islands (higher score, then shorter, then older)."""
    bests = [e for e in best_per_island(archive) if e is not None]
    if not bests:
        raise ValueError("the archive is empty; build it with new_archive(seed, config)")
    return max(bests, key=_better_key)


def top_entries(archive: Archive, k: int) -> tuple[Entry, ...]:
    """The ``k`` best entries over all islands with distinct sources, best first.

    Used to collect the variable requests of the top skeletons when the search stalls.
    """
    by_source: dict[str, Entry] = {}
    for island in archive.islands:
        for entry in island.entries:
            old = by_source.get(entry.source)
            if old is None or _better_key(entry) > _better_key(old):
                by_source[entry.source] = entry
    return tuple(sorted(by_source.values(), key=_better_key, reverse=True)[: max(k, 0)])


# --------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------


def _sample_island(island: Island, config: ArchiveConfig, n: int, u: np.ndarray) -> list[Entry]:
    """``n`` distinct entries of ``island`` by the cluster and length softmaxes; 2n uniforms."""
    groups = clusters(island, config)
    if not groups:
        return []
    phi = np.array([-_log_error(c.score, config.nmse_floor) for c in groups])
    cluster_logits = _minmax(phi) / config.tau_c
    length_logits = [
        -_minmax(np.array([e.length for e in c.entries], dtype=np.float64)) / config.tau_l
        for c in groups
    ]
    left = [np.ones(len(c.entries), dtype=bool) for c in groups]
    chosen: list[Entry] = []
    for i in range(min(n, len(island.entries))):
        alive = np.array([m.any() for m in left])
        c = _choose(np.where(alive, cluster_logits, -np.inf), u[2 * i])
        j = _choose(np.where(left[c], length_logits[c], -np.inf), u[2 * i + 1])
        left[c][j] = False
        chosen.append(groups[c].entries[j])
    return chosen


def sample_examples(
    archive: Archive, key: jax.Array, island: int | None = None
) -> tuple[int, tuple[Entry, ...]]:
    """Draw the in-context examples of one prompt.

    Returns ``(island, examples)``: the island (uniform if not given; new candidates from this
    prompt should be registered there) and up to ``examples_per_prompt`` distinct entries,
    ordered worst to best.
    """
    config = archive.config
    n = config.examples_per_prompt
    u = _uniforms(key, 1 + 2 * n)
    if island is None:
        island = min(int(u[0] * len(archive.islands)), len(archive.islands) - 1)
    else:
        island = _check_island(archive, island)
    chosen = _sample_island(archive.islands[island], config, n, u[1:])
    return island, tuple(sorted(chosen, key=_better_key))


def diverse_parents(archive: Archive, key: jax.Array, k: int) -> tuple[Entry, ...]:
    """Up to ``k`` entries with distinct sources, one from each of ``k`` distinct islands.

    The islands are chosen uniformly without replacement; within each, one entry is drawn by the
    cluster and length softmaxes. Ordered worst to best. Useful for crossover-style prompts.
    """
    m = len(archive.islands)
    k = max(0, min(k, m))
    u = _uniforms(key, m + 2 * m)
    order = np.argsort(u[:m], kind="stable")
    parents: dict[str, Entry] = {}
    for rank, island in enumerate(order):
        if len(parents) == k:
            break
        drawn = _sample_island(archive.islands[int(island)], archive.config, 1, u[m + 2 * rank :])
        if drawn and drawn[0].source not in parents:
            parents[drawn[0].source] = drawn[0]
    return tuple(sorted(parents.values(), key=_better_key))


# --------------------------------------------------------------------------------------------
# Reset
# --------------------------------------------------------------------------------------------


def reset_weak_islands(archive: Archive, key: jax.Array) -> Archive:
    """Empty the weaker half of the islands and re-seed each from a random survivor's best.

    Islands are ranked by their best score, ties (equal to :data:`jaxdmd.ties.SIGNIFICANT`
    digits: islands holding the same seed are equal, whatever their last bits) broken at random
    (so equal islands are reset fairly); the ``n_islands // 2`` lowest are reset. Each reset
    island receives the best entry of a surviving island chosen uniformly at random
    (independently per reset island).
    """
    m = len(archive.islands)
    n_reset = m // 2
    if n_reset == 0:
        return archive
    u = _uniforms(key, m + n_reset)
    bests = best_per_island(archive)
    scores = np.array([-np.inf if e is None else settled(e.score) for e in bests])
    order = np.lexsort((u[:m], scores))  # ascending score, random among ties
    weak, strong = order[:n_reset], order[n_reset:]
    islands = list(archive.islands)
    for i, k in enumerate(weak):
        donor = bests[int(strong[min(int(u[m + i] * len(strong)), len(strong) - 1)])]
        islands[int(k)] = Island(() if donor is None else (donor,))
    return dataclasses.replace(archive, islands=tuple(islands))


def maybe_reset(archive: Archive, key: jax.Array, current_round: int) -> Archive:
    """``reset_weak_islands`` if ``current_round`` is a positive multiple of ``reset_period``."""
    period = archive.config.reset_period
    if period > 0 and current_round > 0 and current_round % period == 0:
        return reset_weak_islands(archive, key)
    return archive


# --------------------------------------------------------------------------------------------
# Per-equation recombination
# --------------------------------------------------------------------------------------------


def _pool(archive: Archive, n_eq: int) -> list[Entry]:
    return [e for e in top_entries(archive, archive.size) if len(e.losses) == n_eq]


def best_lines(archive: Archive) -> tuple[Entry, ...]:
    """For each equation ``j``, the entry with the lowest ``losses[j]`` over all islands.

    Only entries with as many equations as the overall best entry are considered. Ties go to the
    better entry overall (higher score, then shorter, then older).
    """
    n_eq = len(best(archive).losses)
    pool = _pool(archive, n_eq)  # best first, so min() keeps the better entry on ties
    return tuple(min(pool, key=lambda e, j=j: e.losses[j]) for j in range(n_eq))


def recombine(archive: Archive, max_plans: int = 4) -> list[Recombination]:
    """Recombination plans expected to beat the best entry, best expected score first.

    The plans are: every equation from its best donor (``best_lines``), and the best entry with
    a single equation replaced by that equation's best donor. Plans with a single donor, or whose
    expected score does not beat the best entry, are left out; an empty list means nothing to
    recombine.
    """
    base = best(archive)
    lines = best_lines(archive)
    n_eq = len(lines)
    candidates = [lines]
    for j in range(n_eq):
        if lines[j].source != base.source:
            candidates.append(tuple(lines[j] if i == j else base for i in range(n_eq)))
    plans: dict[tuple[str, ...], Recombination] = {}
    for donors in candidates:
        sources = tuple(d.source for d in donors)
        if len(set(sources)) < 2 or sources in plans:
            continue
        plan = Recombination(donors, tuple(d.losses[j] for j, d in enumerate(donors)))
        if settled(plan.score) > settled(base.score):
            plans[sources] = plan
    ranked = sorted(plans.values(), key=lambda p: settled(p.score), reverse=True)
    return ranked[: max(max_plans, 0)]


# --------------------------------------------------------------------------------------------
# Serialisation
# --------------------------------------------------------------------------------------------


def _float_to_json(x: float) -> float | str:
    return x if math.isfinite(x) else repr(x)  # 'inf', '-inf', 'nan': strict JSON has no inf


def _float_from_json(x: float | str) -> float:
    return float(x)


def _entry_to_dict(entry: Entry) -> dict:
    return {
        "source": entry.source,
        "score": _float_to_json(entry.score),
        "losses": [_float_to_json(x) for x in entry.losses],
        "params": [_float_to_json(x) for x in entry.params],
        "length": entry.length,
        "round": entry.round,
        "requests": json.loads(json.dumps(entry.requests)),
    }


def _entry_from_dict(d: Mapping[str, Any]) -> Entry:
    return Entry(
        source=d["source"],
        score=_float_from_json(d["score"]),
        losses=tuple(_float_from_json(x) for x in d["losses"]),
        params=tuple(_float_from_json(x) for x in d["params"]),
        length=d["length"],
        round=d["round"],
        requests=tuple(d.get("requests", ())),
    )


def to_dict(archive: Archive) -> dict:
    """A strict-JSON-serialisable dict of ``archive`` (``json.dumps(..., allow_nan=False)``)."""
    return {
        "format": "jaxdmd.archive",
        "version": FORMAT_VERSION,
        "config": dataclasses.asdict(archive.config),
        "islands": [[_entry_to_dict(e) for e in island.entries] for island in archive.islands],
    }


def from_dict(d: Mapping[str, Any]) -> Archive:
    """The archive saved by ``to_dict``."""
    if d.get("format") != "jaxdmd.archive" or d.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"not a jaxdmd archive of format version {FORMAT_VERSION}: "
            f"format={d.get('format')!r}, version={d.get('version')!r}"
        )
    config = ArchiveConfig(**d["config"])
    islands = tuple(Island(tuple(_entry_from_dict(e) for e in es)) for es in d["islands"])
    return Archive(islands, config)
