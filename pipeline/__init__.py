"""Generic engine for content-addressed, resumable pipeline steps. Imports nothing model-specific.

Modules (each small, stdlib-only at import time):
    stage      the stage contract: Stage, Resources, StageContext, build_params, ParamsError
    errors     UserError and the user-error rule (subclass UserError, or class attribute user_error = True)
    dag        External, Step, compute_keys, dry_run, resolve_results
    keys       what a key hashes (canonical params, upstream keys, input hashes, environment, salt)
    canonical  canonical JSON (sorted keys, 1.0 == 1, shortest float repr)
    hashing    content hashes of user files/folders, memoised by (path, size, mtime_ns)
    store      Store: objects/, tmp/, scratch/, leases/, quarantine/, pins/; publish, lookup, verify, gc
    lease      Lease: per-key exclusive lease files with a heartbeat thread (no flock)
    context    StepContext: checkpoints, progress (tqdm / quiet lines / progress.json), record, log
    engine     Job, Outcome, execute_job: compute one key in whatever process runs it
    executors  SerialExecutor, ProcessPoolExecutor, RayExecutor, make_executor
    runner     run_steps(steps, *, registry, store, executor, run_dir, quiet=False) -> RunResult
    runrecord  runs/<run>/run.json and logs/; referenced_keys (gc roots)
    status     workflow_status: done / running (progress) / partial / failed / pending per step

Typical use (the `dualnerf run` command does this):

    store = Store(cache_dir)
    result = run_steps(steps, registry=stages.STAGES, store=store,
                       executor=make_executor("process", jobs=2), run_dir=runs_dir / run_name)
    for failure in result.failed: print(failure.label, failure.error, failure.log_path)
"""
