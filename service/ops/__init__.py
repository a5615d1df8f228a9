"""Running the process: the HTTP server's connection limits (``server.py``), numba's kernel cache at start
(``kernel_cache.py``), log lines (``logs.py``) and the Prometheus metrics (``metrics.py``). This package
imports nothing itself.
"""
