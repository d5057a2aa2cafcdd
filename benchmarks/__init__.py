"""surfelslam's benchmarks, run as modules from the repository root: ``python -m benchmarks.run_all`` (``make bench``),
``python -m benchmarks.icp_pairs``, ... (each module's docstring has its usage)."""
