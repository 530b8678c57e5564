import os
import signal

# Tests share 2 cores; keep each torch process to one thread unless a test says otherwise.
os.environ.setdefault("OMP_NUM_THREADS", "1")

pytest_plugins = ["tests.scene_fixtures", "tests.e2e_fixtures"]

# Tests interrupt their subprocesses with SIGINT (Ctrl-C). A shell that starts pytest in the background
# (`pytest &`, nohup) ignores SIGINT, and an ignored signal stays ignored in every child: those runs would
# then compute to the end instead of stopping. Give this process, and so its children, the default.
signal.signal(signal.SIGINT, signal.default_int_handler)
