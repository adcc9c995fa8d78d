"""ROS-free evaluation: TUM trajectory files, error measures against ground truth (evo), plots.

Kept apart from the nodes so ``fixego eval``, ``fixego replay`` and the benchmarks share one
implementation of the file format and of the papers' measures.
"""

from fixego_ros.evaluation.tum import TumError, TumWriter, format_tum_line, read_tum, write_tum

__all__ = ['TumError', 'TumWriter', 'format_tum_line', 'read_tum', 'write_tum']
