"""Abutting and cross-cutting between fracture sets: the relative timing a trace network records.

A trace that ends against another (a T end, Sanderson & Nixon's Y node) stopped at a fracture that was
already there, so where the traces of one set end against another set's far more often than the other way
round, the first set is the younger (Hancock 1985, J. Struct. Geol. 7; Peacock et al. 2018, J. Struct.
Geol. 106); crossings (X) say the two sets cut each other. fractopo's
`determine_crosscut_abutting_relationships` counts the same for each pair of sets of a 2D map (its x, y
and y-reverse); here the pairs within a set count too (a set whose traces end against each other), and
each pair's abutting is tested against no preference (a two-sided binomial test of one direction's share).

The counts come from the end codes and the contacts the topology found (`engine.topology`): an end counts
when its code is T and it lies against a trace (`abutting_ends`); a T set by hand where no trace is within
the tolerance is counted apart, as are contacts with a trace of no set (non-systematic, or unlabelled on a
map), which a relation between sets cannot place. On the outcrop, traced bedding is a pseudo-set of its own
("bedding", last): the ends of a set against it say how far the set is bound by the beds (Gross 1993,
J. Struct. Geol. 15); bedding has no ends of its own, so that pair is not tested.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import binomtest

from engine.errors import InputError
from engine.traces import NETWORK_KINDS, Trace3D, network

BEDDING = "bedding"
"""The label of bedding traces among the sets."""
PAIR_COLUMNS = ("set_a", "set_b", "crossings", "a_ends_against_b", "b_ends_against_a", "binomial_p")


@dataclass(frozen=True)
class PairRelation:
    """Two sets' contacts: `crossings` (X nodes), the ends of `first`'s traces against `second`'s and the
    reverse, and the two-sided binomial p-value of that split under no preference (NaN without an abutting
    end, or within one set, where `second_abuts` is None: the set's own ends against its own traces are
    `first_abuts`)."""

    first: str
    second: str
    crossings: int
    first_abuts: int
    second_abuts: int | None
    p_value: float

    @property
    def within(self) -> bool:
        return self.first == self.second

    def describe(self) -> str:
        """One line for a person."""
        if self.second == BEDDING:
            return f"set {self.first} and bedding: {_count(self.first_abuts, 'end')} of set {self.first} against bedding"
        if self.within:
            return (f"set {self.first} with itself: {_count(self.crossings, 'crossing')}, "
                    f"{_count(self.first_abuts, 'end')} against its own traces")
        ends = self.first_abuts + self.second_abuts
        line = f"sets {self.first} and {self.second}: {_count(self.crossings, 'crossing')}"
        if not ends:
            return line + ", no end of either against the other"
        major, minor = ((self.first, self.second) if self.first_abuts >= self.second_abuts
                        else (self.second, self.first))
        share = max(self.first_abuts, self.second_abuts)
        return (line + f"; set {major} ends against set {minor} in {share} of {ends} abutting ends "
                f"(binomial p {self.p_value:.2g}"
                + (f": set {major} the younger)" if self.p_value < 0.05 and share * 2 > ends else ")"))


@dataclass(frozen=True)
class SetRelations:
    """Contacts between sets. `sets` their labels in order; `abuts` (k, k): [a, b] ends of set a's traces
    against set b's traces; `crosses` (k, k), symmetric: crossings between a and b (the diagonal within a
    set). `unplaced`: T ends against no trace found; `unset`: T ends and crossings with a trace of no set."""

    sets: tuple[str, ...]
    abuts: np.ndarray
    crosses: np.ndarray
    unplaced: int
    unset: int

    def pairs(self) -> list[PairRelation]:
        """Every pair of sets, each set with itself first: (0, 0), (0, 1), …, (1, 1), …; bedding (last) only
        with each set, its share of ends untested (bedding has no ends of its own)."""
        out = []
        for a in range(len(self.sets)):
            for b in range(a, len(self.sets)):
                if self.sets[b] == BEDDING and a == b:
                    continue
                ab, ba = int(self.abuts[a, b]), int(self.abuts[b, a])
                p = (binomtest(ab, ab + ba).pvalue if a != b and ab + ba and self.sets[b] != BEDDING
                     else float("nan"))
                out.append(PairRelation(self.sets[a], self.sets[b], int(self.crosses[a, b]), ab,
                                        None if a == b else ba, float(p)))
        return out

    def rows(self) -> list[tuple]:
        """The pairs in PAIR_COLUMNS order, for CSV (empty cells where a value does not apply)."""
        return [(p.first, p.second, p.crossings, p.first_abuts, "" if p.second_abuts is None else p.second_abuts,
                 "" if np.isnan(p.p_value) else p.p_value) for p in self.pairs()]

    def to_dict(self) -> dict:
        """For summary.json: the pairs and the contacts left out."""
        pairs = [{"sets": [p.first, p.second], "crossings": p.crossings, "first_ends_against_second": p.first_abuts,
                  "second_ends_against_first": p.second_abuts,
                  "binomial_p": None if np.isnan(p.p_value) else p.p_value} for p in self.pairs()]
        return {"pairs": pairs, "t_ends_against_no_trace": self.unplaced, "contacts_with_no_set": self.unset}

    def describe(self) -> list[str]:
        """Lines for a person: each pair, then what was left out."""
        lines = [p.describe() for p in self.pairs()]
        if self.unplaced or self.unset:
            lines.append(f"left out: {self.unplaced} T ends against no trace, {self.unset} contacts with a trace "
                         "of no set")
        return lines


def set_relations(sets: Sequence[str | None], terminations: Sequence[tuple[str, str]], abutting: np.ndarray,
                  crossings: np.ndarray, *, names: Sequence[str] | None = None) -> SetRelations:
    """Count the abutting ends and crossings between and within sets (module docstring).

    sets : the set label of each trace, None (or "") for none. terminations : (start, end) codes of each
    trace. abutting : (n, 2) the trace each end lies against, -1 for none (`engine.topology.abutting_ends`).
    crossings : (K, 2) the two traces of each crossing (`engine.topology.Crossings.traces`).
    names : the sets in the order to report them (default: every label, in natural order: "2" before "10").
    """
    names = tuple(sorted({s for s in sets if s}, key=_natural) if names is None else names)
    index = {s: k for k, s in enumerate(names)}
    group = np.array([index.get(s, -1) if s else -1 for s in sets], dtype=int)
    abutting = np.asarray(abutting, dtype=int).reshape(-1, 2)
    is_t = np.array([[code == "T" for code in pair] for pair in terminations], dtype=bool).reshape(-1, 2)
    trace, _ = np.nonzero(is_t)
    other = abutting[is_t]
    placed = other >= 0
    a, b = group[trace[placed]], group[other[placed]]
    crossings = np.asarray(crossings, dtype=int).reshape(-1, 2)
    ca, cb = group[crossings[:, 0]], group[crossings[:, 1]]
    k = len(names)
    abuts = np.zeros((k, k), dtype=int)
    both = (a >= 0) & (b >= 0)
    np.add.at(abuts, (a[both], b[both]), 1)
    crosses = np.zeros((k, k), dtype=int)
    kept = (ca >= 0) & (cb >= 0)
    np.add.at(crosses, (ca[kept], cb[kept]), 1)
    crosses = crosses + crosses.T - np.diag(np.diag(crosses))
    return SetRelations(names, abuts, crosses, int((~placed).sum()), int((~both).sum() + (~kept).sum()))


def _count(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _natural(label: str) -> tuple:
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", label) if part)


def outcrop_relations(traces: Sequence[Trace3D], contacts: dict) -> SetRelations:
    """The relations of 3D traces as they are now (their sets and end codes) over the `contacts` stored by
    the last analysis (`contacts_result`); non-systematic traces are in no set, bedding traces are the
    pseudo-set "bedding" (whose ends are no fracture's: it only takes ends), and a contact with a trace gone
    since (merged, deleted) is left out."""
    abutting, crossings = stored_contacts(traces, contacts)
    labels = [BEDDING if t.kind not in NETWORK_KINDS else str(t.set_id) if t.set_id >= 0 else None for t in traces]
    names = [str(i) for i in sorted({t.set_id for t in network(traces) if t.set_id >= 0})]
    codes = [(t.term_start, t.term_end) if t.kind in NETWORK_KINDS else ("", "") for t in traces]
    return set_relations(labels, codes, abutting, crossings, names=names + ([BEDDING] if BEDDING in labels else []))


def contacts_result(traces: Sequence[Trace3D], abutting: np.ndarray, crossings: np.ndarray) -> dict:
    """The contacts of an analysis by trace id, as stored with its topology: [id, end (0 start, 1 end),
    id of the trace it lies against] per abutting end, [id, id] per crossing."""
    ids = np.array([t.id for t in traces], dtype=np.int64)
    trace, end = np.nonzero(np.asarray(abutting).reshape(-1, 2) >= 0)
    against = np.asarray(abutting).reshape(-1, 2)[trace, end]
    pairs = ids[np.asarray(crossings, dtype=int).reshape(-1, 2)]
    return {"abutting": np.column_stack([ids[trace], end, ids[against]]).tolist(), "crossings": pairs.tolist()}


def stored_contacts(traces: Sequence[Trace3D], contacts: dict) -> tuple[np.ndarray, np.ndarray]:
    """`contacts_result` back as indices into `traces`: abutting (n, 2) and crossings (K, 2)."""
    index = {t.id: k for k, t in enumerate(traces)}
    try:
        abutting = np.full((len(traces), 2), -1)
        for trace, end, other in contacts["abutting"]:
            if trace in index and other in index:
                abutting[index[trace], int(end)] = index[other]
        crossings = [(index[a], index[b]) for a, b in contacts["crossings"] if a in index and b in index]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(None, f"the stored contacts of the last analysis are damaged ({exc}); run `tracemap "
                               "analyse` again") from None
    return abutting, np.array(crossings, dtype=int).reshape(-1, 2)
