"""Thread defaults of the demo, the training / evaluation CLI and the test suite, in one place.

These are machine-dependent choices; ``benchmarks/threads.py`` measured them (numbers in
``docs/performance-history.md``, "Threads under load"). Imports nothing, so that a script can read it before
torch is imported.

On a 2-core machine (torch 2.13 CPU, libgomp), demo image pre-training steps took:

=============================  ===========  ===========  =====================
load                           1 thread     2 threads    2 threads, PASSIVE
=============================  ===========  ===========  =====================
no competitor                  0.10-0.16 s  0.06-0.13 s  0.13-0.49 s
one busy matmul process        0.13 s       0.37 s       0.28 s
one busy small-ops process x2  0.13-0.18 s  5.0 s        0.62 s
=============================  ===========  ===========  =====================

Two intra-op threads gain at most 2x on an idle machine and lose up to 40x when another process
keeps a core busy (each OpenMP parallel region waits for the thread the competitor descheduled, and
libgomp's default policy spins while waiting). One thread never lost more than 1.5x. Hence one
thread by default; ``OMP_WAIT_POLICY=PASSIVE`` is left to the user: it only matters with several
threads, where it limits the loss under load (5.0 -> 0.6 s) but costs up to 4x on an idle machine.
"""

#: torch intra-op threads used by ``examples/train_demo.py``, ``python -m mssf_examples`` and the tests
#: unless ``--threads`` says otherwise.
DEFAULT_THREADS = 1

__all__ = ["DEFAULT_THREADS"]
