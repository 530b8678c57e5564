import os

# Tests share 2 cores; keep each torch process to one thread unless a test says otherwise.
os.environ.setdefault("OMP_NUM_THREADS", "1")

pytest_plugins = ["tests.scene_fixtures"]
