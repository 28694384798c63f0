"""The hand-written readings of the docs quote figures of the generated blocks: each
reading listed here is found, word for word, in its document, and the figures it
quotes are computed again from the block it reads (its tables, or a line of the block).
A block regenerated with other numbers, or a reading edited, fails here until the two
agree again.

A reading is a phrase of the document (whitespace as in one line) and a function of the
blocks that returns the words the phrase must contain: its figures, written as the
phrase writes them (rounded, or as a word). Only readings whose figures follow from a
block are listed; a qualitative reading ("far above", "the same basin") is not checked
here."""

import math
import re
import tomllib
from collections.abc import Callable
from typing import NamedTuple

import pytest

from experiments import blocks
from fojax.optimize.strategies import METHODS

NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
WORDS = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 10: "ten"}
ORDINALS = {1: "highest", 2: "second highest", 3: "third highest", 4: "fourth", 5: "fifth"}


class Blocks:
    """The generated blocks of a checkout, read on demand: their text and tables."""

    def __init__(self, read: Callable[[str], str]):
        self._read = read  # document (relative path) -> its content

    def text(self, name: str) -> str:
        block = blocks.BLOCKS[name]
        found = blocks.block_text(self._read(block.document), block)
        assert found is not None, f"{block.document} has no block {name}"
        return found

    def tables(self, name: str) -> list[list[dict[str, str]]]:
        """Every Markdown table of the block ``name``: its rows, each header -> cell."""
        found, current = [], []
        for line in [*self.text(name).splitlines(), ""]:
            if line.startswith("|"):
                current.append([c.strip() for c in line.strip().strip("|").split(" | ")])
            elif current:
                header, _, *rows = current
                found.append([dict(zip(header, row, strict=False)) for row in rows])
                current = []
        return found


class Reading(NamedTuple):
    document: str
    phrase: str
    figures: Callable[[Blocks], list[str]]


def number(cell: str) -> float:
    """The first number of a table cell ("1.84e+03 [1.83e+03, 1.85e+03]" -> 1840.0)."""
    found = NUMBER.search(cell)
    assert found is not None, f"no number in {cell!r}"
    return float(found.group())


def sig(x: float, digits: int = 2) -> str:
    """``x`` to ``digits`` significant figures, written without an exponent."""
    rounded = round(x, digits - 1 - math.floor(math.log10(abs(x))))
    return f"{rounded:g}" if abs(rounded) < 1e5 else str(int(rounded))


def claim(holds: bool, words: str) -> str:
    """``words`` where the table bears them out, else words no phrase holds."""
    return words if holds else f"(not so: {words})"


def _row(rows, **cells) -> dict:
    (found,) = [r for r in rows if all(r.get(k) == v for k, v in cells.items())]
    return found


# ------------------------------------------------------------------ the readings


def _chattering_ratios(b: Blocks) -> list[str]:
    # The 33-parameter default's scenario 3 chattering against every other 33-parameter
    # row but CMA-ES from the paper's gains.
    runs = b.tables("tuning-study")[0]
    column = "scenario 3: roll/pitch torque chattering (N m)"
    rows = [r for r in runs if r["parameters"] == "33"]
    default = number(_row(rows, start="naive", method="default (`auto`)")[column])
    others = [
        number(r[column])
        for r in rows
        if r["method"] != "default (`auto`)" and (r["start"], r["method"]) != ("paper", "CMA-ES")
    ]
    return [f"{sig(default / max(others))} to {sig(default / min(others))} times"]


def _gradient_ranks(b: Blocks) -> list[str]:
    runs = b.tables("tuning-study")[0]
    rank = {}
    for parameters in ("33", "66"):
        rows = [r for r in runs if r["parameters"] == parameters and r["start"] == "naive"]
        order = sorted(rows, key=lambda r: -number(r["held-out cost"]))
        rank[parameters] = {r["method"]: i + 1 for i, r in enumerate(order)}
        assert len(order) == 6
    lbfgs = {rank[p]["L-BFGS"] for p in rank}
    chain = {p: ORDINALS[rank[p]["CMA-ES then L-BFGS"]] for p in rank}
    return [
        claim(lbfgs == {1}, "L-BFGS with the highest cost of the six methods in both settings"),
        f"the {chain['66']} (66 parameters) or the {chain['33']} (33)",
    ]


def _study_times(b: Blocks) -> list[str]:
    per_run = b.tables("tuning-study")[1]
    longest = max(number(r["wall time (s)"]) for r in per_run)
    spread = max(number(line.rsplit("within ", 1)[1]) for line in _tallies(b))
    return [
        claim(longest <= 120, "every run within 120 s"),
        claim(spread < 1, "the three seeds of each setting within 1 % of each other"),
    ]


def _tallies(b: Blocks) -> list[str]:
    return [line for line in b.text("tuning-study").splitlines() if "seeds within" in line]


def _fair_steps(b: Blocks) -> list[str]:
    steps = [number(r["steps run"]) for r in b.tables("fair-comparison")[-1]]
    return [f"after {min(steps):.0f} to {max(steps):.0f} of the {METHODS['auto'].steps} steps"]


def _fair_against_study(b: Blocks) -> list[str]:
    fair = _row(b.tables("fair-comparison")[-1], controller="afonftsmc")
    study = _row(b.tables("tuning-study")[1], parameters="33", start="paper", seed="0")
    study_steps = number(
        _row(
            b.tables("tuning-study")[0], parameters="33", start="paper", method="default (`auto`)"
        )["steps (returned step)"]
    )
    same = number(fair["steps run"]) == study_steps
    return [
        claim(fair["tuned parameters"] == "33", "the study's 33-parameter run"),
        claim(same, f"the same {study_steps:.0f} steps"),
        f"in {fair['tuning wall time (s)']} s here against {study['wall time (s)']} s there",
    ]


def _mean_terms(b: Blocks) -> dict[str, list[float]]:
    line = next(s for s in b.text("tune-paper-gains").splitlines() if s.startswith("Mean terms"))
    terms = line.split(": ", 1)[1].rstrip(".")
    return {
        part.split(" ", 1)[0]: [float(x) for x in part.split(" ", 1)[1].split(" / ")]
        for part in terms.split(", ")
    }


def _paper_gains_chattering(b: Blocks) -> list[str]:
    terms = _mean_terms(b)
    ratios = [terms["default"][3] / terms[n][3] for n in ("gradient", "cma-es", "nelder-mead")]
    words = f"{WORDS[math.floor(min(ratios))]} to {WORDS[math.ceil(max(ratios))]} times"
    return [f"`C` close to the paper's gains' and {words} the other tuned sets'"]


def _paper_gains_scenario3(b: Blocks) -> list[str]:
    costs = {r["gains"]: number(r["scenario 3 (50 s)"]) for r in b.tables("tune-paper-gains")[0]}
    ratio = costs["default"] / costs["paper"]
    return [claim(3.5 <= ratio < 4, "their cost is nearly four times the paper's")]


def _remark3(b: Blocks) -> list[str]:
    table = b.tables("remark3")[1]
    at = {}
    for row in table:
        if row["field"].startswith("**"):
            at[(row["field"].strip("*"), row["axes"].strip("`"))] = row
    paper = {k: number(v["paper"]) for k, v in at.items()}
    from_paper = {k: number(v["tuned from paper"]) for k, v in at.items()}
    naive = {k: number(v["tuned from naive"]) for k, v in at.items()}
    factors = [
        max(
            number(r["tuned from naive"]) / number(r["naive"]),
            number(r["naive"]) / number(r["tuned from naive"]),
        )
        for r in table
        if not r["field"].startswith("**")
    ]
    j = ("J = P + A", "sat")
    orders = [math.log10(naive[(t, "sat")] / paper[(t, "sat")]) for t in ("E", "C")]
    orders_paper = [math.log10(from_paper[(t, "sat")] / paper[(t, "sat")]) for t in ("E", "C")]
    return [
        claim(paper[j] / from_paper[j] > 10, "ends more than ten times lower in `J`"),
        claim(round(naive[j] / from_paper[j]) == 2, "about twice as high in `J`"),
        f"within a factor of about {WORDS[round(max(factors))]} of the naive ones",
        claim(
            round(paper[("P", "sat")] / naive[("P", "sat")]) == 10,
            "its position term `P` is about a tenth of the paper's",
        ),
        claim(
            round(naive[("A", "sat")] / paper[("A", "sat")]) == 5,
            "its attitude term `A` about five times the paper's",
        ),
        f"its effort and chattering {WORDS[math.floor(min(orders))]} to "
        f"{WORDS[math.ceil(max(orders))]} orders of magnitude above",
        claim({round(x) for x in orders_paper} == {5}, "about five orders of magnitude above"),
    ]


def _vehicles_tuned(b: Blocks) -> list[str]:
    tables = b.tables("vehicles")
    tuned = [t for t in tables if "tuned from naive: steps, time (s)" in t[0]]
    assert len(tuned) == 2
    rmse = [number(r["RMSE, 80 s"]) for t in tuned for r in t]
    times = [float(r["tuned from naive: steps, time (s)"].split(", ")[1]) for t in tuned for r in t]
    return [
        f"tracks at {sig(100 * min(rmse))}-{sig(100 * max(rmse))} cm RMSE",
        claim(max(times) <= 80, "No tuning run took more than 80 s"),
    ]


def _iris_authority(b: Blocks) -> list[str]:
    # The block's largest torques of the Iris over the inertia of its file.
    heading = next(s for s in b.text("vehicles").splitlines() if s.startswith("#### iris"))
    roll, pitch, _ = (
        float(x) for x in heading.split("largest torques ")[1].split(" N m")[0].split(", ")
    )
    vehicle = tomllib.loads((blocks.ROOT / "examples/vehicles/iris.toml").read_text())
    ix, iy, _ = (round(x, 3) for x in vehicle["vehicle"]["inertia"]["value"])
    return [
        f"{roll / ix:.0f} rad/s^2 in roll and {pitch / iy:.0f} rad/s^2 in pitch "
        f"({roll:g} N m over {ix:g} kg m^2, {pitch:g} N m over {iy:g} kg m^2)"
    ]


def _verdicts(name: str) -> Callable[[Blocks], list[str]]:
    def figures(b: Blocks) -> list[str]:
        table = next(t for t in b.tables(name) if "verdict" in t[0])
        scenario = [r for r in table if r["claim"].startswith("Scenario")]
        failing = [r for r in scenario if r["verdict"] == "**does not hold**"]
        return [f"{WORDS[len(failing)].capitalize()} of the {WORDS[len(scenario)]} scenario claims"]

    return figures


def _draws(b: Blocks) -> list[str]:
    settings = next(s for s in b.text("reproduction").splitlines() if s.startswith("Settings:"))
    return [f"({settings.split('Settings: ')[1].split(' draws')[0]} draws, a margin"]


def _within_two_percent(b: Blocks) -> list[str]:
    tallies = [s for s in b.text("tuning-study").splitlines() if "33 and 66 parameters:" in s]
    both = len(tallies) == 2 and all("within 2 % in 6/6" in s for s in tallies)
    return [claim(both, "within 2 % of the best-known cost")]


def _undecided(b: Blocks) -> list[str]:
    table = next(t for t in b.tables("reproduction") if "verdict" in t[0])
    row = next(r for r in table if r["claim"].startswith("Scenario 2: 'rejection"))
    counts = [int(x) for x in row["better / worse / equivalent / undecided"].split(" / ")]
    return [claim(counts[:3] == [0, 0, 0], f"none of its {counts[3]} comparisons is")]


READINGS = [
    Reading(
        "docs/tuning.md",
        "and pitch torque chattering 3.4 to 160 times that of the other 33-parameter rows",
        _chattering_ratios,
    ),
    Reading(
        "docs/tuning.md",
        "from the naive start L-BFGS with the highest cost of the six "
        "methods in both settings, CMA-ES then L-BFGS with the third highest (66 "
        "parameters) or the fourth (33)",
        _gradient_ranks,
    ),
    Reading(
        "docs/tuning.md",
        "Every run ends within 2 % of the best-known cost, and the three "
        "seeds of each setting within 1 % of each other (the tallies under the run table), "
        "and every run within 120 s",
        _study_times,
    ),
    Reading(
        "docs/tuning.md",
        "Every run stopped at its convergence test, after 161 to 206 of the 240 steps allowed",
        _fair_steps,
    ),
    Reading(
        "docs/tuning.md",
        "the AFONFTSMC's run here has the problem, start, seed and method "
        "of the study's 33-parameter run from the paper's gains with seed 0 and stops after "
        "the same 206 steps, in 202 s here against 62 s there",
        _fair_against_study,
    ),
    Reading(
        "docs/tuning.md",
        "a chattering term `C` close to the paper's gains' and three to "
        "four times the other tuned sets'",
        _paper_gains_chattering,
    ),
    Reading(
        "docs/tuning.md",
        "scenario 3 their cost is nearly four times the paper's",
        _paper_gains_scenario3,
    ),
    Reading(
        "docs/tuning.md",
        "L-BFGS from the paper's gains ends more than ten times lower in `J`",
        lambda b: _remark3(b)[:1],
    ),
    Reading(
        "docs/tuning.md",
        "ends about twice as high in `J` as from the paper's gains, with "
        "gains within a factor of about three of the naive ones: its position term `P` is "
        "about a tenth of the paper's, its attitude term `A` about five times the paper's, "
        "its effort and chattering two to three orders of magnitude above the paper's",
        lambda b: _remark3(b)[1:6],
    ),
    Reading(
        "docs/tuning.md",
        "chattering `C` are about five orders of magnitude above the paper's",
        lambda b: _remark3(b)[6:],
    ),
    Reading(
        "docs/vehicles.md",
        "every tuned controller tracks at 3.5-6.6 cm RMSE. No tuning run took more than 80 s",
        _vehicles_tuned,
    ),
    Reading(
        "docs/vehicles.md",
        "give 72 rad/s^2 in roll and 34 rad/s^2 in pitch (2.52 N m "
        "over 0.035 kg m^2, 1.56 N m over 0.046 kg m^2)",
        _iris_authority,
    ),
    Reading(
        "docs/reproduction.md",
        "Four of the five scenario claims do not hold",
        _verdicts("reproduction"),
    ),
    Reading(
        "docs/reproduction.md",
        "is *inconclusive*: none of its 8 comparisons is decided",
        _undecided,
    ),
    Reading("README.md", "(100 draws, a margin of practical size)", _draws),
    Reading(
        "README.md",
        "four of the five scenario claims do not hold",
        _verdicts("reproduction"),
    ),
    Reading(
        "README.md",
        "the same gains from the paper's gains as from a start that knows nothing of them, "
        "within 2 % of the best-known cost",
        _within_two_percent,
    ),
    Reading(
        "docs/reproduction_sat.md",
        "Four of the five scenario claims do not hold",
        _verdicts("reproduction-sat"),
    ),
]


# ---------------------------------------------------------------------- checking


def _flat(text: str) -> str:
    return " ".join(text.split())


def check(reading: Reading, found: Blocks, read: Callable[[str], str]) -> list[str]:
    """What is wrong with ``reading``: not in its document, or a figure the blocks give
    that its phrase does not quote."""
    if _flat(reading.phrase) not in _flat(read(reading.document)):
        return [f"{reading.document}: no reading {reading.phrase!r}"]
    return [
        f"{reading.document}: {reading.phrase!r} should quote {words!r} (from the block)"
        for words in reading.figures(found)
        if _flat(words).lower() not in _flat(reading.phrase).lower()
    ]


def _read(document: str) -> str:
    return (blocks.ROOT / document).read_text()


@pytest.mark.parametrize("reading", READINGS, ids=[r.phrase[:40] for r in READINGS])
def test_each_reading_quotes_its_block_s_figures(reading):
    assert check(reading, Blocks(_read), _read) == []


def test_a_reading_whose_figure_the_block_does_not_give_fails():
    # The tuning study's table with the 33-parameter default's chattering doubled: the
    # reading's "3.4 to 160" no longer follows from it.
    def altered(document: str) -> str:
        text = _read(document)
        return text.replace("| 1.84e+03 [1.83e+03, 1.85e+03] |", "| 3.68e+03 [3.66e+03, 3.7e+03] |")

    reading = READINGS[0]
    assert check(reading, Blocks(_read), _read) == []
    assert check(reading, Blocks(altered), altered) == [
        f"docs/tuning.md: {reading.phrase!r} should quote '6.8 to 320 times' (from the block)"
    ]
    edited = reading._replace(phrase=reading.phrase.replace("3.4", "4"))
    assert check(edited, Blocks(_read), _read) == [f"docs/tuning.md: no reading {edited.phrase!r}"]
