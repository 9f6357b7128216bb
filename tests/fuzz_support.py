"""What the fuzz tests (tests/test_fuzz_*.py) share: the property every reader of user input
must hold, hostile values, and mutations of a valid document.

The property (issue 32): a reader returns a valid result or raises a typed error
(:class:`cutterpose.errors.CutterposeError`) whose message is one line; never another
exception, never more than :data:`TIME_S` seconds for one input, and the process's peak memory
grows by less than :data:`MEMORY_MB` over a whole test (:class:`MemoryBound`).

Example counts: ``examples(n)`` gives ``n`` in CI (the ``ci`` profile: derandomized, so a run
sees the inputs of the last one) and ``FUZZ_FACTOR * n`` under ``HYPOTHESIS_PROFILE=fuzz``
(``make fuzz``: random inputs, a local example database).
"""

from __future__ import annotations

import copy
import math
import os
import resource
import time

from hypothesis import strategies as st

from cutterpose.errors import CutterposeError

#: one input, read or refused, in at most this many seconds (two shared cores)
TIME_S = 2.0
#: a whole fuzz test grows the process's peak memory by less than this
MEMORY_MB = 200
FUZZ = os.environ.get("HYPOTHESIS_PROFILE") == "fuzz" and not os.environ.get("CI")
FUZZ_FACTOR = 50


def examples(n: int) -> int:
    """``n`` examples in CI, ``FUZZ_FACTOR * n`` in ``make fuzz``."""
    return n * FUZZ_FACTOR if FUZZ else n


def typed_or_valid(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``: its result, or the typed error it raised (checked: one line,
    not empty); any other exception propagates and fails the test; slower than ``TIME_S``
    fails it too."""
    t0 = time.perf_counter()
    try:
        out = fn(*args, **kwargs)
    except CutterposeError as e:
        msg = str(e).strip()
        assert msg, f"{type(e).__name__} without a message"
        assert "\n" not in msg, f"{type(e).__name__} message of several lines: {msg!r}"
        assert len(msg) <= 1000, f"{type(e).__name__} message of {len(msg)} characters"
        out = e
    dt = time.perf_counter() - t0
    assert dt < TIME_S, f"{dt:.2f} s for one input"
    return out


class MemoryBound:
    """``with MemoryBound(): ...`` fails when the process's peak RSS grew by ``MEMORY_MB``."""

    def __enter__(self):
        self.base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return self

    def __exit__(self, *exc):
        grow_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - self.base) / 1024
        if exc[0] is None:
            assert grow_mb < MEMORY_MB, f"peak memory grew by {grow_mb:.0f} MB"


#: numbers and values a careless or hostile file holds
HOSTILE = [math.nan, math.inf, -math.inf, 0, -1, -0.0, 1e-320, 1e308, -1e308, 10 ** 30,
           2 ** 63, -2 ** 63, 10 ** 400, True, False, None, "", "1", "abc", "nan", [], {},
           [1, 2], [[1, 2], [3]], {"a": 1}, "x" * 10000]

hostile_values = st.one_of(
    st.sampled_from(HOSTILE), st.floats(), st.integers(), st.text(max_size=20),
    st.lists(st.floats(), max_size=20))

json_trees = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(), st.integers(), st.text(max_size=12),
              st.sampled_from(HOSTILE)),
    lambda kids: st.lists(kids, max_size=5) | st.dictionaries(st.text(max_size=8), kids,
                                                              max_size=5),
    max_leaves=25)


def _paths(doc, prefix=()):
    """Every path (tuple of keys / indices) to a node below ``doc``."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) \
        if isinstance(doc, list) else ()
    for k, v in items:
        yield (*prefix, k)
        yield from _paths(v, (*prefix, k))


@st.composite
def mutated(draw, doc, n_max: int = 3):
    """``doc`` (a JSON-like tree) with 1..``n_max`` nodes replaced by hostile values or
    random trees, deleted, or given an extra key."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, n_max))):
        paths = list(_paths(doc))
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        op = draw(st.sampled_from(["value", "value", "tree", "delete", "add"]))
        # copies: a drawn value may be one of HOSTILE's lists or dicts, which a later
        # mutation would otherwise change for every following example
        if op == "delete":
            del parent[key]
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.text(max_size=8))] = copy.deepcopy(draw(hostile_values))
        else:
            parent[key] = copy.deepcopy(draw(hostile_values if op == "value" else json_trees))
    return doc


@st.composite
def mutated_bytes(draw, data: bytes):
    """``data`` truncated, with bytes flipped, or with a slice inserted or removed."""
    data = bytearray(data)
    op = draw(st.sampled_from(["truncate", "flip", "flip", "insert", "delete"]))
    if op == "truncate":
        return bytes(data[: draw(st.integers(0, max(len(data) - 1, 0)))])
    if op == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] = draw(st.integers(0, 255))
        return bytes(data)
    i = draw(st.integers(0, len(data)))
    if op == "insert":
        return bytes(data[:i] + draw(st.binary(min_size=1, max_size=64)) + data[i:])
    return bytes(data[:i] + data[i + draw(st.integers(1, 64)):])
