"""Benchmarks (see bench/run.py). Importing the package pins BLAS to one thread before any
benchmark imports numpy: two benchmark workers on two cores, each with BLAS threads of its
own, spin against each other (see x6wd.app.cli.single_thread_blas)."""

from x6wd.app.cli import single_thread_blas

single_thread_blas()
