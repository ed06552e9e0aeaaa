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
here runs a torch op before forking, so no thread pool is inherited. The extra ranks that
Lightning's DDP launcher starts for such a child are forked the same way (spares, below).

Protocol, JSON lines: requests on stdin ``{"argv", "cwd", "env", "stdout", "stderr",
"session"}``; answers on the original stdout ``{"started": pid}`` in request order and
``{"exited": pid, "rc": code}`` as children end (``rc`` is negative for a signal, as in
:mod:`subprocess`).
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import select
import subprocess
import sys
import tempfile

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
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)  # stdin is this process's request pipe
    os.close(devnull)
    for fd, name in ((1, "stdout"), (2, "stderr")):
        out = os.open(spec[name], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(out, fd)
        os.close(out)
    _RANKS.extend(_fork_rank_spares(_ranks_to_spare(spec["argv"])))
    subprocess.Popen = _RankPopen  # type: ignore[misc]
    _become_cli(spec["argv"], spec["cwd"], spec["env"])


def _become_cli(argv: list[str], cwd: str, env: dict[str, str]) -> None:
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    tempfile.tempdir = None  # chosen afresh from this command's TMPDIR, not the parent's
    sys.path[0] = cwd  # what `python -m` puts first, where this script's folder was
    for entry in reversed(env.get("PYTHONPATH", "").split(os.pathsep)):
        if entry and entry not in sys.path:
            sys.path.insert(1, entry)
    # Lightning's DDP launcher restarts `python -m <__main__.__spec__.name> argv[1:]`.
    main_spec = importlib.util.find_spec("occtrain.__main__")
    sys.modules["__main__"].__spec__ = main_spec
    sys.argv = [main_spec.origin, *argv]  # as `python -m occtrain` sets it
    raise SystemExit(occtrain.cli.main(argv))


# Lightning's DDP launcher starts each extra rank as a new interpreter (`python -m
# occtrain.__main__ ARGV` with the rank in its environment), 8-10 s of imports per rank
# and stage. A child asked to train on several devices forks spares of itself before it
# runs anything (so, like this process, they hold imports and no thread pool); each waits
# on a pipe for one such command and becomes it. They are the launcher's own children
# (it waits on them, signals them, reads their exit codes) in its process group, as the
# interpreters it would start; a command that is not occtrain's, or one past the spares,
# starts as it would have.
_RANKS: list[tuple[int, int]] = []  # (pid, the pipe its command goes down)
_RANK_COMMAND = ("-m", "occtrain.__main__")


def _ranks_to_spare(argv: list[str]) -> int:
    """Spares for a command: a few per extra device asked for (one launch per stage that
    trains on several), none for a one-process run."""
    devices = [int(a.rpartition("=")[2]) for a in argv if re.search(r"(^|\.)devices=\d+$", a)]
    return 4 * (max(devices, default=1) - 1)


def _fork_rank_spares(count: int) -> list[tuple[int, int]]:
    spares: list[tuple[int, int]] = []
    for _ in range(count):
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(write)
            for _, other in spares:
                os.close(other)
            _serve_as_rank(read)
        os.close(read)
        spares.append((pid, write))
    return spares


def _serve_as_rank(pipe: int) -> None:
    """Wait for a command; run it as its own program would. Unused (the pipe closed with
    the launcher gone or done): end quietly."""
    with os.fdopen(pipe, "rb") as fh:
        text = fh.read()
    if not text:
        os._exit(0)
    spec = json.loads(text)
    _become_cli(spec["argv"], spec["cwd"], spec["env"])


class _RankPopen(subprocess.Popen):
    """:class:`subprocess.Popen`, whose child for an occtrain rank command is a spare."""

    def _execute_child(
        self, args, executable, preexec_fn, close_fds, pass_fds, cwd, env, startupinfo, creationflags, shell,
        p2cread, p2cwrite, c2pread, c2pwrite, errread, errwrite, *rest,
    ):  # fmt: skip
        plain = (p2cread, p2cwrite, c2pread, c2pwrite, errread, errwrite) == (-1,) * 6 and not shell
        if not (_RANKS and plain and tuple(args[1:3]) == _RANK_COMMAND and args[0] == sys.executable):
            return super()._execute_child(
                args, executable, preexec_fn, close_fds, pass_fds, cwd, env, startupinfo, creationflags, shell,
                p2cread, p2cwrite, c2pread, c2pwrite, errread, errwrite, *rest,
            )  # fmt: skip
        pid, pipe = _RANKS.pop(0)
        spec = {"argv": list(args[3:]), "cwd": os.fspath(cwd or os.getcwd()), "env": dict(env or os.environ)}
        with os.fdopen(pipe, "wb") as fh:
            fh.write(json.dumps(spec).encode())
        self.pid = pid
        self._child_created = True


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
