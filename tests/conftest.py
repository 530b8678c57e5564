import os
import signal

import pytest

# Tests share 2 cores; keep each torch process to one thread unless a test says otherwise.
os.environ.setdefault("OMP_NUM_THREADS", "1")

pytest_plugins = ["tests.scene_fixtures", "tests.e2e_fixtures"]

# Tests interrupt their subprocesses with SIGINT (Ctrl-C). A shell that starts pytest in the background
# (`pytest &`, nohup) ignores SIGINT, and an ignored signal stays ignored in every child: those runs would
# then compute to the end instead of stopping. Give this process, and so its children, the default.
signal.signal(signal.SIGINT, signal.default_int_handler)


# Modules whose tests start a local Ray instance or the shared end-to-end reference run (smoke_reference):
# under pytest-xdist one worker runs them all, first, so two Ray instances never compete for the cores, the
# reference run is computed once, and the longest chain of tests starts while the other worker takes the rest.
SHARED_WORKER_MODULES = ("test_cluster", "test_e2e_workflow", "test_pipeline_executors")


def _module_of(nodeid: str) -> str:
    return nodeid.split("::", 1)[0].rsplit("/", 1)[-1].removesuffix(".py")


def pytest_collection_modifyitems(config, items):
    """The shared-worker modules' tests first (a stable sort: every other test keeps its place)."""
    items.sort(key=lambda item: _module_of(item.nodeid) not in SHARED_WORKER_MODULES)


@pytest.hookimpl(optionalhook=True)          # a hook of pytest-xdist, which the plain `pytest` run lacks
def pytest_xdist_make_scheduler(config, log):
    """`-n N --dist loadscope` (Makefile `test`): each module's tests on one worker (its module fixtures are
    computed once), the SHARED_WORKER_MODULES as one unit, units handed out in collection order."""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = _module_of(nodeid)
            return "shared-worker" if module in SHARED_WORKER_MODULES else nodeid.split("::", 1)[0]

    config.option.loadscopereorder = False       # keep collection order: the shared unit goes out first
    return ModuleScheduling(config, log)
