"""Training runs as child processes, N at a time, with a progress bar, stopped with a checkpoint.

``safenav bench gym|safe`` and ``safenav tune`` run each of their trials as one child process
(``python -m safenav train ...`` or an SB3 script) and need the same things around it: a queue
that keeps ``jobs`` children running, a bar per child read from its progress file, a log file per
child, and, when the parent is interrupted (Ctrl-C, ``kill``), each child stopped with SIGTERM so
that it writes its checkpoint and a rerun resumes it. :func:`run_queue` does that for any list of
:class:`ChildRun`.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ChildRun:
    """One child run: how to start it, how far it is, and what to do when it exits with 0."""

    name: str
    steps: int
    command: Callable[[], list[str]]
    """The command line, built when the child starts (a resumed run's differs)."""
    steps_done: Callable[[], int]
    """How far it has come (read from its progress file; polled while it runs)."""
    finish: Callable[[float], str]
    """Called with its wall clock (s) after exit code 0: writes its result, returns one line to
    print; an exception it raises fails this run alone (the others go on)."""
    log: Path


def stop_children(procs: list[subprocess.Popen], say: Callable[[str], None],
                  timeout_s: float = 300.0) -> None:  # fmt: skip
    """The parent was interrupted (Ctrl-C, ``kill``): let each running child checkpoint and stop
    before the parent exits, so that none trains on as an orphan (a rerun would then find its run
    directory in use). The children run in their own sessions, so a Ctrl-C at the terminal
    reaches the parent alone, and the parent sends each one SIGTERM, once. A child still running
    after ``timeout_s`` is killed (its last periodic checkpoint stays)."""
    live = [p for p in procs if p.poll() is None]
    if not live:
        return
    say(f"stopping {len(live)} running trial(s); safenav trials write a checkpoint, and the same "
        "command resumes them")  # fmt: skip
    for proc in live:
        proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    for proc in live:
        try:
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_queue(runs: list[ChildRun], jobs: int, say: Callable[[str], None], progress: bool = True,
              console=None) -> list[str]:  # fmt: skip
    """Run ``runs``, ``jobs`` at a time, each a child process; returns a line per failed run.
    Ctrl-C or SIGTERM stops the running children with a checkpoint (:func:`stop_children`) and
    is raised again as ``KeyboardInterrupt``."""
    from safenav.common.stopping import enable_sigint

    enable_sigint()  # SIGTERM raises here too, so that the children are stopped with it
    running: dict[str, tuple[ChildRun, subprocess.Popen, object, float, object]] = {}
    try:
        return _run(runs, jobs, running, say, progress, console)
    except KeyboardInterrupt:
        stop_children([proc for _, proc, *_ in running.values()], say)
        raise


def _run(runs: list[ChildRun], jobs: int, running: dict, say: Callable[[str], None],
         progress: bool, console) -> list[str]:  # fmt: skip
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from safenav.common.stopping import die_with_parent

    failures: list[str] = []
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())  # fmt: skip
    with Progress(*columns, console=console, disable=not progress) as bar:
        overall = bar.add_task("all trials (env steps)", total=sum(r.steps for r in runs))
        queue = list(runs)
        finished_steps = 0
        while queue or running:
            while queue and len(running) < jobs:
                run = queue.pop(0)
                run.log.parent.mkdir(parents=True, exist_ok=True)
                log = run.log.open("a")
                # Its own session: Ctrl-C reaches the parent only, which stops each child once
                # (stop_children); and SIGTERM when the parent dies, however it dies.
                preexec = die_with_parent if sys.platform.startswith("linux") else None
                task = bar.add_task(run.name, total=run.steps)
                proc = subprocess.Popen(run.command(), stdout=log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True,
                                        preexec_fn=preexec)  # fmt: skip
                # at once, with nothing between: stop_children must see every child started
                running[run.name] = (run, proc, log, time.perf_counter(), task)
            time.sleep(0.5 if progress else 0.2)
            live = 0
            for name, (run, proc, log, t0, task) in list(running.items()):
                done = min(run.steps_done(), run.steps)
                bar.update(task, completed=done)
                if proc.poll() is None:
                    live += done  # a finished run counts once, in finished_steps
                    continue
                log.close()
                bar.remove_task(task)
                del running[name]
                finished_steps += run.steps
                if proc.returncode != 0:
                    failures.append(f"{name}: exit {proc.returncode} (log: {run.log})")
                    say(failures[-1])
                    continue
                try:
                    say(run.finish(time.perf_counter() - t0))
                except Exception as err:  # noqa: BLE001  (any bad result fails this run alone)
                    failures.append(f"{name}: {type(err).__name__}: {err}")
                    say(failures[-1])
            bar.update(overall, completed=finished_steps + live)
    return failures


__all__ = ["ChildRun", "run_queue", "stop_children"]
