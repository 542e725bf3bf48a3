"""Tests of the island archive (jaxdmd.archive)."""

import dataclasses
import json
import math
from collections import Counter

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxdmd  # noqa: F401  (float64)
from jaxdmd import archive as ar


def entry(source, nmse, length=10, rnd=0, losses=None, params=(1.0,), requests=()):
    """An entry with score -nmse; losses default to nmse for each of two equations."""
    losses = (nmse, nmse) if losses is None else losses
    return ar.Entry(source, -nmse, losses, params, length, rnd, requests)


SEED = entry("seed", 1.0, length=5)


def keys(n, seed=0):
    """``n`` distinct keys (cheaper than iterating over a split key array)."""
    return [jax.random.key(100_000 * seed + i) for i in range(n)]


def one_island(entries, **config):
    config = ar.ArchiveConfig(n_islands=1, **config)
    return ar.register_many(ar.new_archive(entries[0], config), entries[1:], 0)


def sample_sources(archive, n, island=0, seed=0):
    return [
        tuple(e.source for e in ar.sample_examples(archive, k, island)[1]) for k in keys(n, seed)
    ]


def assert_frequencies(counts, expected, n):
    """Each empirical frequency within 5 standard deviations of its expected probability."""
    for name, p in expected.items():
        sigma = math.sqrt(max(p * (1 - p), 1e-4) / n)
        assert abs(counts.get(name, 0) / n - p) < 5 * sigma, (name, counts, expected)


# ------------------------------------------------------------------------------------------
# Building and registering
# ------------------------------------------------------------------------------------------


def test_new_archive_seeds_every_island():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=7))
    assert len(a.islands) == 7
    assert all(island.entries == (SEED,) for island in a.islands)
    assert ar.best(a) == SEED
    with pytest.raises(ValueError, match="seed"):
        ar.new_archive(entry("bad", math.inf), ar.ArchiveConfig(n_islands=2))


def test_register_returns_new_archive_and_leaves_original_unchanged():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=3))
    before = ar.to_dict(a)
    b = ar.register(a, entry("x", 0.1), 1)
    assert ar.to_dict(a) == before
    assert a.islands[1].entries == (SEED,)
    assert [len(i.entries) for i in b.islands] == [1, 2, 1]
    assert b.islands[0] is a.islands[0]  # untouched islands are shared
    with pytest.raises(dataclasses.FrozenInstanceError):
        b.islands = ()
    with pytest.raises(dataclasses.FrozenInstanceError):
        b.islands[1].entries[1].score = 0.0


def test_register_into_all_islands():
    a = ar.register(ar.new_archive(SEED, ar.ArchiveConfig(n_islands=3)), entry("x", 0.1), None)
    assert all(len(i.entries) == 2 for i in a.islands)


def test_register_dedupes_identical_source_keeping_the_better():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=2))
    worse, better = entry("x", 0.5, rnd=1), entry("x", 0.1, rnd=2)
    for first, second in [(worse, better), (better, worse)]:
        b = ar.register(ar.register(a, first, 0), second, 0)
        assert b.islands[0].entries == (SEED, better)
    # the same source on another island is a different island member
    c = ar.register(ar.register(a, worse, 0), better, 1)
    assert c.islands[0].entries[-1] == worse and c.islands[1].entries[-1] == better


def test_register_ignores_non_finite_scores():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=2))
    for bad in (math.inf, math.nan):
        e = entry("dropped", bad)
        assert not e.is_valid
        assert ar.register(a, e, 0) is a
        assert ar.register(a, e, None) is a


def test_entry_validation():
    with pytest.raises(ValueError, match="-NMSE"):
        ar.Entry("x", 0.5, (0.5,), (), 3, 0)
    with pytest.raises(TypeError, match="JSON"):
        ar.Entry("x", -0.5, (0.5,), (), 3, 0, ({"f": object()},))
    e = ar.Entry("x", np.float64(-0.5), np.array([0.5]), [1, 2], np.int64(3), 0, {"a": 1})
    assert e.losses == (0.5,) and e.params == (1.0, 2.0) and e.requests == ({"a": 1},)
    assert type(e.score) is float and type(e.length) is int


def test_requests_are_decoupled_from_the_callers_dicts():
    request = {"name": "i_d", "kind": "algebraic"}
    e = entry("x", 0.1, requests=(request,))
    request["name"] = "changed"
    assert e.requests[0]["name"] == "i_d"


def test_register_rejects_a_bad_island_index():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=2))
    with pytest.raises(IndexError, match="island"):
        ar.register(a, entry("x", 0.1), 2)


def test_capacity_drops_the_worst_entries():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=1, max_entries_per_island=3))
    a = ar.register_many(a, [entry(f"e{i}", 10.0**-i) for i in range(1, 5)], 0)
    assert [e.source for e in a.islands[0].entries] == ["e2", "e3", "e4"]


def test_invalid_config_says_what_is_wrong():
    with pytest.raises(ValueError, match="tau_c"):
        ar.ArchiveConfig(tau_c=0.0)
    with pytest.raises(ValueError, match="n_islands"):
        ar.Archive((), ar.ArchiveConfig(n_islands=2))


# ------------------------------------------------------------------------------------------
# Clusters and queries
# ------------------------------------------------------------------------------------------


def test_clusters_group_by_relative_error_on_a_log_scale():
    island = ar.Island(
        (entry("a", 1.00e-3), entry("b", 1.01e-3), entry("c", 1.2e-3), entry("d", 1e-1))
    )
    groups = ar.clusters(island, ar.ArchiveConfig())
    assert [tuple(e.source for e in c.entries) for c in groups] == [("d",), ("c",), ("a", "b")]
    assert groups[-1].score == pytest.approx(-1.005e-3)
    # an exact fit is well defined (nmse_floor)
    assert len(ar.clusters(ar.Island((entry("p", 0.0), entry("q", 1e-15))), ar.ArchiveConfig()))


def test_best_and_best_per_island():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=3))
    a = ar.register(a, entry("x", 0.1), 0)
    a = ar.register(a, entry("y", 0.01, length=20), 2)
    a = ar.register(a, entry("z", 0.01, length=12), 2)
    assert [e.source for e in ar.best_per_island(a)] == ["x", "seed", "z"]
    assert ar.best(a).source == "z"  # equal score: the shorter one
    assert [e.source for e in ar.top_entries(a, 3)] == ["z", "y", "x"]


# ------------------------------------------------------------------------------------------
# Sampling
# ------------------------------------------------------------------------------------------


LADDER = [entry(f"c{i}", 10.0 ** -(i + 1)) for i in range(4)]  # c0 worst ... c3 best


def test_sample_returns_distinct_entries_worst_to_best():
    a = one_island([SEED, *LADDER], examples_per_prompt=3, tau_c=5.0)
    for k in keys(100):
        island, examples = ar.sample_examples(a, k)
        assert island == 0 and len(examples) == 3
        assert len({e.source for e in examples}) == 3
        scores = [e.score for e in examples]
        assert scores == sorted(scores)


def test_sample_returns_fewer_when_the_island_is_small():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=2, examples_per_prompt=3))
    assert ar.sample_examples(a, jax.random.key(0))[1] == (SEED,)
    a = ar.register(a, entry("x", 0.1), 1)
    island, examples = ar.sample_examples(a, jax.random.key(0), island=1)
    assert island == 1 and examples == (SEED, a.islands[1].entries[1])


def test_low_cluster_temperature_picks_the_best_cluster():
    a = one_island(LADDER, examples_per_prompt=1, tau_c=0.01)
    assert set(sample_sources(a, 150)) == {("c3",)}


def test_high_cluster_temperature_is_near_uniform():
    n = 1200
    a = one_island(LADDER, examples_per_prompt=1, tau_c=1e4)
    counts = Counter(s[0] for s in sample_sources(a, n))
    assert_frequencies(counts, {f"c{i}": 0.25 for i in range(4)}, n)


def test_cluster_probabilities_are_the_softmax_of_normalised_log_scores():
    n, tau = 1200, 0.2
    a = one_island(LADDER, examples_per_prompt=1, tau_c=tau)
    counts = Counter(s[0] for s in sample_sources(a, n))
    # log10 errors -1..-4, normalised to 0, 1/3, 2/3, 1
    p = np.exp(np.array([0, 1, 2, 3]) / 3 / tau)
    p /= p.sum()
    assert_frequencies(counts, {f"c{i}": p[i] for i in range(4)}, n)


def test_clusters_are_drawn_by_mean_score_not_by_size():
    # three near-identical skeletons in a bad cluster must not outweigh one good skeleton
    bad = [entry(f"b{i}", 0.1 * (1 + 1e-4 * i)) for i in range(3)]
    a = one_island([*bad, entry("good", 1e-3)], examples_per_prompt=1, tau_c=1e4)
    assert len(ar.clusters(a.islands[0], a.config)) == 2
    n = 1200
    counts = Counter("good" if s[0] == "good" else "bad" for s in sample_sources(a, n))
    assert_frequencies(counts, {"good": 0.5, "bad": 0.5}, n)


def test_length_preference_within_a_cluster():
    same_score = [entry(f"l{n}", 1e-2, length=n) for n in (10, 20, 30)]
    n = 1200
    low = one_island(same_score, examples_per_prompt=1, tau_l=0.01)
    assert set(sample_sources(low, 150)) == {("l10",)}
    high = one_island(same_score, examples_per_prompt=1, tau_l=1e4)
    counts = Counter(s[0] for s in sample_sources(high, n))
    assert_frequencies(counts, {"l10": 1 / 3, "l20": 1 / 3, "l30": 1 / 3}, n)
    mid = one_island(same_score, examples_per_prompt=1, tau_l=0.2)
    counts = Counter(s[0] for s in sample_sources(mid, n))
    p = np.exp(-np.array([0.0, 0.5, 1.0]) / 0.2)
    p /= p.sum()
    assert_frequencies(counts, {"l10": p[0], "l20": p[1], "l30": p[2]}, n)


def test_sampling_is_invariant_to_multiplicative_rescaling_of_scores():
    rng = np.random.default_rng(0)
    # log10 errors on the cluster grid (+0.002, away from rounding boundaries), some shared
    logs = rng.integers(-500, 0, size=12) / 100 + 0.002
    logs[3] = logs[7]
    lengths = rng.integers(5, 60, size=12)

    def build(factor):
        config = ar.ArchiveConfig(n_islands=3, examples_per_prompt=3)
        seed = entry("seed", 1.0 * factor, length=5)
        a = ar.new_archive(seed, config)
        for i, (lg, n) in enumerate(zip(logs, lengths, strict=True)):
            a = ar.register(a, entry(f"s{i}", factor * 10.0**lg, length=int(n)), i % 3)
        return a

    reference = build(1.0)
    for factor in (10.0, 1e-3, 10.0**0.5):
        scaled = build(factor)
        for k in keys(80, seed=1):
            (i0, e0), (i1, e1) = ar.sample_examples(reference, k), ar.sample_examples(scaled, k)
            assert i0 == i1
            assert [e.source for e in e0] == [e.source for e in e1]


def test_sampling_is_deterministic_given_the_key():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4, examples_per_prompt=2))
    a = ar.register_many(a, LADDER, [0, 1, 2, 3])
    a = ar.register_many(a, [entry(f"x{i}", 0.05 * (i + 1), length=i) for i in range(8)], None)
    k = jax.random.key(42)
    assert ar.sample_examples(a, k) == ar.sample_examples(a, k)
    assert ar.sample_examples(a, jax.random.PRNGKey(3)) == ar.sample_examples(
        a, jax.random.PRNGKey(3)
    )
    outcomes = {ar.sample_examples(a, k) for k in keys(50)}
    assert len(outcomes) > 5


def test_islands_are_chosen_uniformly():
    n = 1200
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4))
    counts = Counter(ar.sample_examples(a, k)[0] for k in keys(n))
    assert_frequencies(counts, {i: 0.25 for i in range(4)}, n)


def test_diverse_parents_come_from_distinct_islands():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4))
    a = ar.register_many(a, LADDER, [0, 1, 2, 3])
    a = ar.register_many(a, [entry(f"y{i}", 0.3) for i in range(4)], [0, 1, 2, 3])
    for k in keys(50):
        parents = ar.diverse_parents(a, k, 3)
        assert 1 <= len(parents) <= 3
        assert len({p.source for p in parents}) == len(parents)
        assert [p.score for p in parents] == sorted(p.score for p in parents)
        assert ar.diverse_parents(a, k, 3) == parents


# ------------------------------------------------------------------------------------------
# Reset
# ------------------------------------------------------------------------------------------


def test_reset_empties_the_weaker_half_and_reseeds_from_survivors():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4))
    a = ar.register_many(a, LADDER, [0, 1, 2, 3])  # island i best = c_i; 0 and 1 are weak
    before = ar.to_dict(a)
    donors = Counter()
    for k in keys(40):
        b = ar.reset_weak_islands(a, k)
        assert b.islands[2] == a.islands[2] and b.islands[3] == a.islands[3]
        for i in (0, 1):
            assert len(b.islands[i].entries) == 1
            donor = b.islands[i].entries[0]
            assert donor in (LADDER[2], LADDER[3])
            donors[donor.source] += 1
    assert set(donors) == {"c2", "c3"}
    assert ar.to_dict(a) == before
    assert ar.reset_weak_islands(a, jax.random.key(7)) == ar.reset_weak_islands(
        a, jax.random.key(7)
    )


def test_reset_breaks_ties_at_random():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4))
    a = ar.register_many(a, [entry(f"t{i}", 1e-2) for i in range(4)], [0, 1, 2, 3])
    reset = Counter()
    for k in keys(60):
        b = ar.reset_weak_islands(a, k)
        was_reset = [b.islands[i] != a.islands[i] for i in range(4)]
        assert sum(was_reset) == 2
        reset.update(i for i in range(4) if was_reset[i])
    assert set(reset) == {0, 1, 2, 3}


def test_reset_does_not_rank_islands_by_their_last_bits():
    """Four islands whose bests are equally good in exact arithmetic (computed, they differ in
    the last bits, as one line fitted in two batches does): which two are reset is the key's
    choice, the same whichever island carries the rounding."""
    chosen = set()
    for noisy in range(4):
        tied = [entry(f"t{i}", 1e-2 * (1 + 3e-15 * (i == noisy))) for i in range(4)]
        a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4))
        a = ar.register_many(a, tied, [0, 1, 2, 3])
        b = ar.reset_weak_islands(a, jax.random.key(5))
        chosen.add(tuple(b.islands[i] != a.islands[i] for i in range(4)))
    assert len(chosen) == 1


def test_maybe_reset_follows_the_period():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=4, reset_period=4))
    a = ar.register_many(a, LADDER, [0, 1, 2, 3])
    k = jax.random.key(0)
    assert all(ar.maybe_reset(a, k, r) is a for r in (0, 1, 2, 3, 5))
    assert ar.maybe_reset(a, k, 4) == ar.reset_weak_islands(a, k) != a
    never = dataclasses.replace(a, config=dataclasses.replace(a.config, reset_period=0))
    assert ar.maybe_reset(never, k, 4) is never


# ------------------------------------------------------------------------------------------
# Per-equation recombination
# ------------------------------------------------------------------------------------------


def test_best_lines_and_recombination_plans():
    A = entry("A", 0.0667, losses=(1e-4, 1e-1, 1e-1))
    B = entry("B", 0.0667, losses=(1e-1, 1e-4, 1e-1))
    C = entry("C", 1e-2, losses=(1e-2, 1e-2, 1e-2))
    other = entry("D", 1e-3, losses=(1e-6, 1e-6))  # other number of equations: ignored
    seed = entry("seed", 1.0, losses=(1.0, 1.0, 1.0))
    a = ar.new_archive(seed, ar.ArchiveConfig(n_islands=3))
    a = ar.register_many(a, [A, B, C], [0, 1, 2])
    assert ar.best_lines(a) == (A, B, C)
    plans = ar.recombine(a)
    assert [tuple(d.source for d in p.donors) for p in plans] == [
        ("A", "B", "C"),
        ("A", "C", "C"),
        ("C", "B", "C"),
    ]
    assert plans[0].losses == (1e-4, 1e-4, 1e-2)
    assert plans[0].score == pytest.approx(-(2e-4 + 1e-2) / 3)
    assert all(p.score > C.score for p in plans)
    assert len(ar.recombine(a, max_plans=1)) == 1
    # once the best entry is best on every equation, there is nothing to recombine
    E = entry("E", 1e-5, losses=(1e-5, 1e-5, 1e-5))
    assert ar.recombine(ar.register(a, E, 0)) == []
    assert ar.best_lines(ar.register(ar.register(a, E, 0), other, 1)) == (E, E, E)


# ------------------------------------------------------------------------------------------
# Serialisation and pytrees
# ------------------------------------------------------------------------------------------


def test_to_dict_from_dict_round_trip_through_strict_json():
    a = ar.new_archive(SEED, ar.ArchiveConfig(n_islands=3, tau_c=0.3, reset_period=2))
    a = ar.register(a, entry("x", 0.1, params=(1.5, -math.inf), requests=({"name": "P_m"},)), 1)
    a = ar.register(a, entry("y", 1 / 3, length=17, rnd=4), 2)
    text = json.dumps(ar.to_dict(a), allow_nan=False)
    b = ar.from_dict(json.loads(text))
    assert b == a
    assert hash(b) == hash(a)
    k = jax.random.key(5)
    assert ar.sample_examples(a, k) == ar.sample_examples(b, k)
    with pytest.raises(ValueError, match="format"):
        ar.from_dict({"islands": []})


def test_archive_is_a_static_pytree():
    a = ar.register(ar.new_archive(SEED, ar.ArchiveConfig(n_islands=2)), entry("x", 0.1), 0)
    assert jax.tree.leaves(a) == []
    assert jax.tree.map(lambda x: x, a) == a

    @eqx.filter_jit
    def f(state):
        archive, x = state
        return x * ar.best(archive).score

    assert float(f((a, jnp.ones(())))) == pytest.approx(-0.1)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, 6),  # source id
            st.sampled_from([1e-6, 1e-3, 0.02, 0.5, 1.0, math.inf]),  # nmse (inf: dropped)
            st.integers(1, 40),  # length
            st.one_of(st.none(), st.integers(0, 2)),  # island
        ),
        max_size=25,
    )
)
def test_register_invariants(ops):
    config = ar.ArchiveConfig(n_islands=3, max_entries_per_island=4)
    a = ar.new_archive(SEED, config)
    best_seen = SEED.score
    for src, nmse, length, island in ops:
        a = ar.register(a, entry(f"s{src}", nmse, length=length), island)
        if math.isfinite(nmse):
            best_seen = max(best_seen, -nmse)
    for island in a.islands:
        sources = [e.source for e in island.entries]
        assert 1 <= len(sources) <= 4
        assert len(set(sources)) == len(sources)
        assert all(math.isfinite(e.score) for e in island.entries)
    assert ar.best(a).score == best_seen
    assert ar.from_dict(json.loads(json.dumps(ar.to_dict(a)))) == a
