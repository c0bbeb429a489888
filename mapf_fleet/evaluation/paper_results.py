"""The paper's own numbers, as data (transcribed from /work/shared/paper/cooperative-mapf-paper.txt).

- Table 4 (appendix): 40x40 maps, 4-64 agents; DHC baseline and alpha 0.1-0.4, DCC baseline and
  alpha 0.1-0.3 (the cooperative exploration curriculum, "proposed").
- Table 1: the same rows on 80x80 maps, 4-128 agents.
- Table 2 (ablation, 80x80): the "w/o CL" rows (a fixed alpha right after stage 1): DHC alpha
  0.2, 0.3, 0.4 and DCC alpha 0.2, 0.3.

Table 2 reaches the text file with its row labels shifted (the algorithm and alpha columns slid by
one row and the last "proposed" row, DCC alpha 0.3, is missing). The rows are identified by their
values: every "Proposed" row of the text equals the Table 1 row of the same algorithm and alpha,
which fixes the remaining "w/o CL" rows as DHC 0.2, 0.3, 0.4, DCC 0.2, 0.3 in that order
(test/test_evaluation_model_card.py checks this against the text).

Success rates are fractions of the 200 test instances; average steps count failures at the
limit (256 steps on 40x40, 386 on 80x80).
"""

from __future__ import annotations

from dataclasses import dataclass

AGENTS_40 = (4, 8, 16, 32, 64)
AGENTS_80 = (4, 8, 16, 32, 64, 128)
AGENTS_BY_SIZE = {40: AGENTS_40, 80: AGENTS_80}
TABLE_BY_SIZE = {40: "Table 4", 80: "Table 1"}

CURRICULUM = "curriculum"  # the paper's method: alpha reached by the cooperative curriculum
FIXED = "w/o CL"  # ablation: fixed alpha right after stage 1 (Table 2)
BASELINE = "baseline"  # alpha 0


@dataclass(frozen=True)
class PaperRow:
    """One row of a table of the paper: one algorithm, one alpha, one map size."""

    table: str  # "Table 1", "Table 2" or "Table 4"
    algorithm: str  # "dhc" | "dcc"
    map_size: int  # 40 or 80
    alpha: float  # 0.0 for the baseline
    method: str  # BASELINE | CURRICULUM | FIXED
    success_rate: dict[int, float]  # agents -> fraction of instances solved
    average_steps: dict[int, float]  # agents -> mean steps, failures at the limit

    @property
    def label(self) -> str:
        name = self.algorithm.upper()
        if self.method == BASELINE:
            return f"{name} baseline"
        suffix = " w/o CL" if self.method == FIXED else ""
        return f"{name} α={self.alpha:g}{suffix}"


def _row(table: str, algorithm: str, size: int, alpha: float, method: str,
         success: tuple[float, ...], steps: tuple[float, ...]) -> PaperRow:
    agents = AGENTS_BY_SIZE[size]
    if len(success) != len(agents) or len(steps) != len(agents):
        raise ValueError(f"paper {table} {algorithm} alpha {alpha}: expected {len(agents)} values per metric")
    return PaperRow(table, algorithm, size, alpha, method, dict(zip(agents, success)), dict(zip(agents, steps)))


# (algorithm, alpha, success rates, average steps) in the paper's row order.
_TABLE_4 = (
    ("dhc", 0.0, (0.990, 0.950, 0.950, 0.820, 0.450), (52.33, 63.90, 79.63, 110.10, 147.26)),
    ("dhc", 0.1, (1.000, 0.925, 0.920, 0.810, 0.525), (58.24, 64.91, 87.25, 102.33, 135.21)),
    ("dhc", 0.2, (1.000, 1.000, 0.970, 0.860, 0.595), (56.58, 59.70, 83.77, 106.31, 138.21)),
    ("dhc", 0.3, (1.000, 1.000, 1.000, 0.920, 0.645), (57.15, 62.09, 81.42, 99.83, 134.86)),
    ("dhc", 0.4, (1.000, 0.995, 0.965, 0.775, 0.430), (60.55, 80.26, 85.23, 237.02, 248.93)),
    ("dcc", 0.0, (1.000, 0.990, 0.990, 0.950, 0.850), (48.58, 59.60, 71.34, 93.54, 135.55)),
    ("dcc", 0.1, (1.000, 1.000, 1.000, 0.985, 0.890), (47.35, 58.43, 73.21, 93.74, 133.73)),
    ("dcc", 0.2, (1.000, 1.000, 1.000, 0.970, 0.905), (47.98, 57.01, 74.79, 94.82, 131.70)),
    ("dcc", 0.3, (0.995, 1.000, 0.980, 0.935, 0.795), (48.99, 56.85, 73.42, 97.10, 156.28)),
)
_TABLE_1 = (
    ("dhc", 0.0, (0.990, 0.980, 0.970, 0.880, 0.720, 0.420), (96.72, 109.24, 122.54, 138.32, 163.5, 213.15)),
    ("dhc", 0.1, (1.000, 0.990, 0.950, 0.845, 0.700, 0.350), (90.21, 103.55, 124.81, 140.9, 159.79, 215.67)),
    ("dhc", 0.2, (1.000, 1.000, 0.960, 0.885, 0.780, 0.460), (88.27, 95.31, 119.08, 142.58, 157.29, 207.85)),
    ("dhc", 0.3, (1.000, 1.000, 0.990, 0.910, 0.825, 0.615), (89.20, 97.35, 116.61, 138.84, 153.44, 204.03)),
    ("dhc", 0.4, (1.000, 0.995, 0.945, 0.850, 0.710, 0.405), (94.64, 110.22, 120.80, 134.79, 165.22, 217.99)),
    ("dcc", 0.0, (1.000, 0.990, 0.975, 0.960, 0.890, 0.820), (93.89, 109.89, 122.24, 132.99, 159.67, 192.9)),
    ("dcc", 0.1, (1.000, 0.995, 0.995, 0.950, 0.900, 0.800), (96.32, 107.34, 119.45, 135.18, 161.86, 198.29)),
    ("dcc", 0.2, (1.000, 1.000, 1.000, 0.970, 0.930, 0.865), (94.10, 113.76, 115.11, 136.56, 154.39, 190.06)),
    ("dcc", 0.3, (1.000, 0.985, 0.935, 0.845, 0.785, 0.635), (93.95, 117.44, 127.37, 139.07, 162.24, 210.74)),
)
# Table 2, "w/o CL" rows only (the "Proposed" rows repeat Table 1).
_TABLE_2_FIXED = (
    ("dhc", 0.2, (0.960, 0.965, 0.925, 0.850, 0.745, 0.415), (99.18, 113.55, 121.76, 139.83, 162.98, 219.64)),
    ("dhc", 0.3, (1.000, 1.000, 0.980, 0.925, 0.810, 0.535), (93.89, 109.89, 122.61, 129.01, 158.92, 210.45)),
    ("dhc", 0.4, (0.980, 1.000, 0.960, 0.900, 0.650, 0.420), (102.76, 105.48, 128.92, 137.24, 189.11, 214.33)),
    ("dcc", 0.2, (1.000, 1.000, 1.000, 0.935, 0.875, 0.835), (93.03, 114.72, 114.69, 140.24, 170.23, 200.51)),
    ("dcc", 0.3, (1.000, 1.000, 0.910, 0.855, 0.610, 0.550), (92.46, 116.34, 129.75, 146.86, 180.24, 215.61)),
)


def _method(alpha: float) -> str:
    return BASELINE if alpha == 0.0 else CURRICULUM


PAPER_ROWS: tuple[PaperRow, ...] = (
    *(_row("Table 4", a, 40, alpha, _method(alpha), s, t) for a, alpha, s, t in _TABLE_4),
    *(_row("Table 1", a, 80, alpha, _method(alpha), s, t) for a, alpha, s, t in _TABLE_1),
    *(_row("Table 2", a, 80, alpha, FIXED, s, t) for a, alpha, s, t in _TABLE_2_FIXED),
)


def paper_rows(algorithm: str | None = None, map_size: int | None = None,
               methods: tuple[str, ...] = (BASELINE, CURRICULUM, FIXED)) -> list[PaperRow]:
    """The paper's rows, filtered; in the paper's order (baseline first, then by alpha)."""
    if algorithm is not None and algorithm not in ("dhc", "dcc"):
        raise ValueError(f"paper_rows: algorithm must be 'dhc' or 'dcc', got {algorithm!r}")
    return [r for r in PAPER_ROWS
            if (algorithm is None or r.algorithm == algorithm)
            and (map_size is None or r.map_size == map_size)
            and r.method in methods]


def paper_row(algorithm: str, map_size: int, alpha: float, method: str | None = None) -> PaperRow | None:
    """The row for this algorithm, map size and alpha (baseline for alpha 0, else the curriculum
    row unless `method` says FIXED); None when the paper has no such row."""
    method = method or _method(alpha)
    for row in paper_rows(algorithm, map_size, (method,)):
        if abs(row.alpha - alpha) < 1e-9:
            return row
    return None
