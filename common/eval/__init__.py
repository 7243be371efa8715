"""Evaluation: what every accuracy figure of the project means.

ATE, RPE and mesh metrics with their alignment (`evaluation`), the per-segment drift and
scale analysis (`drift`), the trajectory plot (`plot`) and the reports that evaluate a run's
output files (`report`). It may import `geometry` and `io`; nothing in the SLAM core imports
it (a run's driver calls it once the run is over).
"""
