"""A warm parent for the tests' ``occtrain`` processes (run as a script by ``conftest``).

A test tool. Most tests call ``occtrain.cli.main`` in their own process
(``conftest.run_cli``); the ones whose point is the process (kill -9, SIGTERM and Ctrl-C,
DDP and FSDP over gloo, torchrun) start a real one (``conftest.run_cli_process``,
``start_cli``, ``kill_at_checkpoint``): a few dozen, each of which would spend 8-10 s
importing torch, Lightning and transformers before reading its arguments, a few minutes of
a suite held to 12. This process imports them once, then forks one child per request; the
child runs ``occtrain.cli.main`` exactly as ``python -m occtrain`` would (its own pid and
exit code, optionally its own session, its stdout and stderr in files, its environment and
working directory), so these tests still drive the real CLI in a separate process. Nothing
here runs a torch op before forking, so no thread pool is inherited.

Protocol, JSON lines: requests on stdin ``{"argv", "cwd", "env", "stdout", "stderr",
"session"}``; answers on the original stdout ``{"started": pid}`` in request order and
``{"exited": pid, "rc": code}`` as children end (``rc`` is negative for a signal, as in
:mod:`subprocess`).
"""

from __future__ import annotations

import importlib.util
import json
import os
import select
import sys

# The imports a `run` or `eval` spends its start-up on.
import lightning  # noqa: F401
import torch  # noqa: F401
import transformers  # noqa: F401

import occtrain.cli
import occtrain.commands.evaluate  # noqa: F401
import occtrain.run.runner  # noqa: F401


def _child(spec: dict) -> None:
    """Become ``python -m occtrain ARGV``: ends by raising SystemExit, which unwinds out of
    :func:`main` and ends this child the way the interpreter ends any program (atexit
    handlers, flushed streams), with the CLI's exit code."""
    if spec.get("session"):
        os.setsid()
    os.chdir(spec["cwd"])
    os.environ.clear()
    os.environ.update(spec["env"])
    sys.path[0] = spec["cwd"]  # what `python -m` puts first, where this script's folder was
    for entry in reversed(spec["env"].get("PYTHONPATH", "").split(os.pathsep)):
        if entry and entry not in sys.path:
            sys.path.insert(1, entry)
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)  # stdin is this process's request pipe
    os.close(devnull)
    for fd, name in ((1, "stdout"), (2, "stderr")):
        out = os.open(spec[name], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(out, fd)
        os.close(out)
    # Lightning's DDP launcher restarts `python -m <__main__.__spec__.name> argv[1:]`.
    main_spec = importlib.util.find_spec("occtrain.__main__")
    sys.modules["__main__"].__spec__ = main_spec
    sys.argv = [main_spec.origin, *spec["argv"]]  # as `python -m occtrain` sets it
    raise SystemExit(occtrain.cli.main(spec["argv"]))


def main() -> None:
    answers = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # a stray print must not corrupt the protocol
    requests = sys.stdin.fileno()
    answers.write(json.dumps({"ready": os.getpid()}) + "\n")
    pending = b""
    while True:
        readable, _, _ = select.select([requests], [], [], 0.05)
        while True:  # reap every child that ended
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            answers.write(json.dumps({"exited": pid, "rc": os.waitstatus_to_exitcode(status)}) + "\n")
        if not readable:
            continue
        chunk = os.read(requests, 1 << 16)
        if not chunk:
            return
        pending += chunk
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            spec = json.loads(line)
            pid = os.fork()
            if pid == 0:
                answers.close()
                _child(spec)  # raises SystemExit: the child never comes back here
            answers.write(json.dumps({"started": pid}) + "\n")


if __name__ == "__main__":
    main()
