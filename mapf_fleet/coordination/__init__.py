"""Coordination layer (numpy only, beside `grid`; no torch, no rclpy): what stands between "each
robot ranks its moves" and "each robot is commanded".

- `pibt`: PIBT with a ranking per agent (CS-PIBT when the orders come from a learned
  policy's Q-values), the tick's arbiter of the evaluator, the trainer's actors (optional), the
  simulator and the real-robot aggregator.
- `ranking`: ranked moves from Q-values, the non-learned heuristic or BFS distances.
- `planners`: the centralized classical references (LaCAM, PIBT from pymapf).
"""
