"""Every shell command of the README and of docs/ runs as written after the README's
set-up: its program is one the set-up installs (``.venv/bin/...``), and its options pass
the command's own parser and the checks it makes before compiling anything. Nothing is
run: the checks are the commands' ``parse_args`` (or ``build_parser``) functions."""

import contextlib
import importlib
import importlib.util
import io
import pathlib
import re
import shlex
import subprocess
import sys
import tomllib
from typing import NamedTuple

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL_BLOCKS = ("bash", "sh", "shell", "console")
FENCE = re.compile(r"^\s*```+\s*([\w+-]*)")
SEPARATORS = {"&&", "||", ";", "|", "&", "(", ")", ";;"}
KEYWORDS = {"do", "then", "else", "elif", "if", "while", "until", "{", "}", "!", "time"}
ENDS = {"done", "fi", "esac"}
VENV = ".venv/bin/"
UNCHECKED = {"git", "cd"}
"""Programs of a documented procedure that are not the project's (their options are
git's and the shell's)."""
LAUNCHERS = {"srun": {"-n", "-N", "-c", "--ntasks", "--nodes", "--cpus-per-task"}}
"""Programs that start the command after them (their options with a value)."""


class Command(NamedTuple):
    page: str
    line: int
    words: tuple[str, ...]
    env: dict

    def __str__(self) -> str:
        return f"{self.page}:{self.line}: {shlex.join(self.words)}"


def _split(text: str) -> list[list[str]]:
    """The simple commands of one logical shell line: words, separators dropped."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=";&|()")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    commands, current = [], []
    for token in lexer:
        if token in SEPARATORS:
            commands.append(current)
            current = []
        else:
            current.append(token)
    commands.append(current)
    return [c for c in commands if c]


def commands_of(text: str, page: str) -> list[Command]:
    """Every simple command of the shell blocks (``bash``, ``sh``, ``shell``, ``console``)
    of Markdown ``text``: backslash continuations joined, split at ``&&``, ``||``, ``;``,
    ``|`` and parentheses, comments, loop headers and shell keywords left out, leading
    ``NAME=value`` assignments kept apart (``env``); in a ``console`` block only the
    lines after a ``$`` prompt."""
    found, language, logical, start = [], None, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        fence = FENCE.match(line)
        if fence:
            language = None if language is not None else fence.group(1).lower()
            continue
        if language not in SHELL_BLOCKS:
            continue
        if language == "console" and not logical:
            if not line.lstrip().startswith("$ "):
                continue
            line = line.lstrip()[2:]
        start = start if logical else number
        if line.rstrip().endswith("\\"):
            logical += line.rstrip()[:-1] + " "
            continue
        logical += line
        for words in _split(logical):
            while words and words[0] in KEYWORDS:
                words = words[1:]
            if not words or words[0] in ENDS or words[0] in ("for", "case", "select"):
                continue
            env = {}
            while words and re.match(r"[A-Za-z_][A-Za-z0-9_]*=", words[0]):
                name, _, value = words.pop(0).partition("=")
                env[name] = value
            if words:
                found.append(Command(page, start, tuple(words), env))
        logical = ""
    return found


def page_commands(page: pathlib.Path) -> list[Command]:
    name = page.relative_to(ROOT) if page.is_relative_to(ROOT) else page.name
    return commands_of(page.read_text(), str(name))


# ------------------------------------------------------------------------ the checks


class Rejected(Exception):
    """A documented command that would not run as written."""


@contextlib.contextmanager
def _exits_are_rejections():
    """argparse's exit (a usage error, status 2, or --help, status 0) as a Rejected
    holding its message, or nothing for status 0."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            yield
    except SystemExit as stop:
        if stop.code not in (0, None):
            message = err.getvalue().strip().splitlines() or [f"exit status {stop.code}"]
            raise Rejected(message[-1]) from None


def _fojax_checks():
    """``fojax COMMAND``'s checks before compiling: each command's ``parse_args``."""
    from fojax.cli import accuracy, bench, reproduce, simulate, tune

    return {
        "simulate": simulate.parse_args,
        "reproduce": reproduce.parse_args,
        "tune": tune.parse_args,
        "bench": bench.parse_args,
        "accuracy": accuracy.parse_args,
    }


RUNTIME = {"simulate", "reproduce", "tune"}
"""The commands that join a jax.distributed run (:func:`fojax.cli.arguments.setup_runtime`)."""


def check_fojax(argv: list[str], env: dict, produced: dict) -> None:
    """``fojax ARGV`` with the variables ``env`` set on its line."""
    from fojax import settings, sharding
    from fojax.cli import COMMANDS, arguments

    try:  # a variable fojax reads must hold a value it can use
        settings.read(env)
    except ValueError as error:
        raise Rejected(str(error)) from None
    if argv in (["--version"], ["--help"], ["-h"]):
        return
    if not argv or argv[0] not in COMMANDS:
        raise Rejected(f"fojax has no command {argv[:1]} (its commands: {sorted(COMMANDS)})")
    command, options = argv[0], argv[1:]
    with _exits_are_rejections():
        _fojax_checks()[command](options)
        if command in RUNTIME:
            _, _, found, chosen = arguments.check_runtime(options, f"fojax {command}", environ=env)
            try:
                sharding.distributed_settings(
                    **chosen, detect=False, names=arguments.DISTRIBUTED_FLAGS, settings=found
                )
            except ValueError as error:
                raise Rejected(str(error)) from None
    if command == "tune":
        produced["tune"] = _value(options, "--out")


def _value(options, flag: str) -> str | None:
    for index, word in enumerate(options):
        if word == flag and index + 1 < len(options):
            return options[index + 1]
        if word.startswith(flag + "="):
            return word.split("=", 1)[1]
    return None


def check_module(module: str, argv: list[str], env: dict, produced: dict) -> None:
    """``python -m MODULE ARGV``: the module exists and its options pass its checks."""
    if module == "fojax.cli" or module == "fojax":
        return check_fojax(argv, env, produced)
    if module.startswith("fojax.cli."):
        name = module.removeprefix("fojax.cli.")
        from fojax.cli import COMMANDS

        if name not in COMMANDS:
            raise Rejected(f"{module} is not a fojax command's module")
        return check_fojax([name, *argv], env, produced)
    if module == "pytest":
        return check_pytest(argv)
    if not module.startswith("experiments."):
        raise Rejected(f"python -m {module}: not a module of this project or its tests")
    if importlib.util.find_spec(module) is None:
        raise Rejected(f"python -m {module}: no such module")
    loaded = importlib.import_module(module)
    with _exits_are_rejections():
        if hasattr(loaded, "parse_args"):
            loaded.parse_args(argv)
        elif hasattr(loaded, "build_parser"):
            loaded.build_parser().parse_args(argv)
        else:
            raise Rejected(f"{module} exposes no parse_args or build_parser to check options")


def check_pytest(argv: list[str]) -> None:
    """pytest's own parser (with this project's conftest options): a collection of one
    small test file with the documented options."""
    probe = ["--collect-only", "-q", "-n", "0", "-p", "no:cacheprovider"]
    done = subprocess.run(
        [sys.executable, "-m", "pytest", *argv, *probe, "tests/test_test_tiers.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    if done.returncode != 0:
        raise Rejected(f"pytest {shlex.join(argv)}: {(done.stderr or done.stdout).strip()[-500:]}")


def _extras() -> set[str]:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return set(pyproject["project"]["optional-dependencies"])


def check_pip(argv: list[str]) -> None:
    """``.venv/bin/pip install``: its files exist, the project's extras are declared."""
    if not argv or argv[0] != "install":
        raise Rejected(f"pip {argv[:1]}: only 'pip install' belongs to the set-up")
    words = argv[1:]
    for index, word in enumerate(words):
        if word in ("-c", "-r", "--constraint", "--requirement"):
            if index + 1 >= len(words) or not (ROOT / words[index + 1]).is_file():
                raise Rejected(f"pip install {word}: no file {words[index + 1 : index + 2]}")
        local = re.fullmatch(r"\.(?:\[([\w,-]+)\])?", word)
        if local and local.group(1):
            unknown = set(local.group(1).split(",")) - _extras()
            if unknown:
                raise Rejected(f"pyproject.toml declares no extra {sorted(unknown)}")


@contextlib.contextmanager
def _import_path(program: str, env: dict):
    """The folders a command imports from besides the installed packages: the current
    folder for ``python -m`` (not for a console script such as ``fojax``), and those of
    ``PYTHONPATH`` set on its line."""
    cwd = str(pathlib.Path.cwd())
    folders = [cwd] if program.endswith("python") else []
    folders += [str(pathlib.Path(p).resolve()) for p in env.get("PYTHONPATH", "").split(":") if p]
    saved = list(sys.path)
    sys.path[:] = folders + [p for p in saved if p not in ("", ".", cwd)]  # this process's own
    importlib.invalidate_caches()
    try:
        yield
    finally:
        sys.path[:] = saved


def check(command: Command, produced: dict) -> None:
    """Raise :class:`Rejected` saying why ``command`` would not run as written."""
    with _import_path(command.words[0], command.env):
        _check(command, produced)


def _check(command: Command, produced: dict) -> None:
    words = list(command.words)
    while words and words[0] in LAUNCHERS:  # srun [options] PROGRAM ...
        takes_value, words = LAUNCHERS[words[0]], words[1:]
        while words and words[0].startswith("-"):
            words = words[2:] if words[0] in takes_value else words[1:]
    if not words:
        raise Rejected("no program")
    program, argv = words[0], words[1:]
    if program in UNCHECKED:
        return
    if program == "python3" and argv[:2] == ["-m", "venv"] and len(argv) == 3:
        return
    if not program.startswith(VENV):
        raise Rejected(
            f"{program!r} is not in the environment the README's set-up makes: "
            f"write {VENV}fojax, {VENV}python or {VENV}pip (the set-up does not activate it)"
        )
    program = program.removeprefix(VENV)
    if program == "fojax":
        return check_fojax(argv, command.env, produced)
    if program == "pip":
        return check_pip(argv)
    if program == "python":
        if len(argv) < 2 or argv[0] != "-m":
            raise Rejected("python without -m MODULE: run the project's modules with -m")
        return check_module(argv[1], argv[2:], command.env, produced)
    raise Rejected(f"{VENV}{program}: the set-up installs no such program")


def _stand_in_gains(folder: pathlib.Path, options) -> None:
    """What a documented ``fojax tune ... --out DIR`` leaves for the commands after it:
    ``DIR/gains.json`` of its controller (the controller's defaults: the checks read the
    file's controller and format, not its values)."""
    from fojax.controllers import gains_io, registry

    law = registry.get_controller_class(_value(options, "--controller"))
    folder.mkdir(parents=True, exist_ok=True)
    gains_io.save_gains(folder / "gains.json", law.name, law.default_gains())


SAVED_AS = re.compile(r"[Ss]aved as `(\w+)\.py`")


def saved_modules(text: str) -> dict[str, str]:
    """``{module: source}`` of the modules a page tells the reader to save: the Python
    block just before each "saved as `NAME.py`"."""
    blocks = [(m.end(), m.group(1)) for m in re.finditer(r"```python\n(.*?)```", text, re.S)]
    modules = {}
    for match in SAVED_AS.finditer(text):
        before = [source for end, source in blocks if end <= match.start()]
        if before:
            modules[match.group(1)] = before[-1]
    return modules


def check_page(page: pathlib.Path, cwd: pathlib.Path) -> list[str]:
    """The problems of ``page``'s commands, in order, from ``cwd`` (a folder that holds
    the repository's files but none of its results): ``file:line: command: why``. A
    documented ``fojax tune --out DIR`` leaves a stand-in ``DIR/gains.json`` for the
    commands after it on the page."""
    problems = []
    for name, source in saved_modules(page.read_text()).items():
        (cwd / f"{name}.py").write_text(source)
    for command in page_commands(page):
        produced = {}
        try:
            check(command, produced)
        except Rejected as why:
            problems.append(f"{command}\n    {why}")
            continue
        if produced.get("tune"):
            options = command.words[command.words.index("tune") + 1 :]
            _stand_in_gains(cwd / produced["tune"], list(options))
    return problems


@pytest.fixture
def clone_view(tmp_path, monkeypatch):
    """A working folder with the repository's files (links) and no results: the place
    a reader runs the documented commands from, after the set-up."""
    for entry in ROOT.iterdir():
        if entry.name not in {"results", ".git"}:
            (tmp_path / entry.name).symlink_to(entry)
    monkeypatch.chdir(tmp_path)
    from fojax.controllers import registry

    monkeypatch.setattr(registry, "_LAWS", dict(registry._LAWS))
    before = set(sys.modules)
    yield tmp_path
    for name in set(sys.modules) - before:  # the modules a page had saved in tmp_path
        if getattr(sys.modules[name], "__file__", None) and str(tmp_path) in str(
            sys.modules[name].__file__
        ):
            del sys.modules[name]


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_every_documented_command_passes_its_checks(page, clone_view):
    problems = check_page(page, clone_view)
    assert not problems, "commands that would not run as written:\n" + "\n".join(problems)


def test_the_pages_hold_the_commands_a_reader_runs():
    found = {p.name: [c.words for c in page_commands(p)] for p in PAGES}
    readme = found["README.md"]
    assert ("python3", "-m", "venv", ".venv") in readme  # the set-up makes .venv
    firsts = {words[:2] for words in readme}
    assert {(".venv/bin/fojax", "simulate"), (".venv/bin/fojax", "tune")} <= firsts
    assert {(".venv/bin/fojax", "reproduce"), (".venv/bin/python", "-m")} <= firsts
    assert sum(len(words) for words in found.values()) > 20


# ------------------------------------------------------------- the checks can fail


def test_the_extraction_reads_blocks_as_a_shell_does():
    text = "\n".join([
        "```bash",
        "# a comment",
        "python3 -m venv .venv && .venv/bin/pip install -c constraints.txt -e \".[tests]\"",
        "A=1 B=two .venv/bin/fojax simulate --scenario 2 \\",
        "    --out results/x   # and more",
        "for r in 1 2; do",
        "  (cd $tree && .venv/bin/fojax bench --small)",
        "done",
        "```",
        "```python",
        "fojax simulate",
        "```",
        "```console",
        "$ .venv/bin/fojax --version",
        "fojax 0.1.0 (output, not a command)",
        "```",
    ])  # fmt: skip
    got = [(c.line, c.words, c.env) for c in commands_of(text, "x.md")]
    assert got == [
        (3, ("python3", "-m", "venv", ".venv"), {}),
        (3, (".venv/bin/pip", "install", "-c", "constraints.txt", "-e", ".[tests]"), {}),
        (4, (".venv/bin/fojax", "simulate", "--scenario", "2", "--out", "results/x"),
         {"A": "1", "B": "two"}),
        (7, ("cd", "$tree"), {}),
        (7, (".venv/bin/fojax", "bench", "--small"), {}),
        (14, (".venv/bin/fojax", "--version"), {}),
    ]  # fmt: skip


TUNE = ".venv/bin/fojax tune --scenario 2 --controller afonftsmc --out results/t"
SIMULATE = ".venv/bin/fojax simulate --scenario 2 --controller afonftsmc --draws 8 --out r/s"


@pytest.mark.parametrize(
    "line, reason",
    [
        ("fojax simulate --scenario 2 --controller afonftsmc --draws 8 --out r", "not in the env"),
        ("python -m experiments.sensitivity", "not in the environment"),
        (".venv/bin/python script.py", "without -m MODULE"),
        (".venv/bin/python -m experiments.no_such_study", "no such module"),
        (".venv/bin/python -m experiments.sensitivity --no-such-option", "unrecognized"),
        (".venv/bin/python -m experiments.sensitivity --controllers fl", "must be among"),
        (".venv/bin/pip install -c no_constraints.txt -e .", "no file"),
        (".venv/bin/pip install -e '.[no_such_extra]'", "declares no extra"),
        (".venv/bin/fojax simulte --out r", "has no command"),
        (f"{TUNE} --device-batch 8", "--device-batch applies to --method"),
        (f"{TUNE} --rotor-limit 2", "--rotor-limit applies with --requirements FILE only"),
        (f"{TUNE} --requirements examples/requirements/none.toml", "does not exist"),
        (f"{SIMULATE} --gains results/none/gains.json", "does not exist"),
        (f"{SIMULATE} --controller fl --switching sat", "--switching does not apply to fl"),
        (f"{SIMULATE} --coordinator node01 --num-processes 2 --process-id 0", "HOST:PORT"),
        (f"{SIMULATE} --coordinator node01:1 --num-processes 2", "--process-id"),
        (f"JAX_NUM_PROCESSES=2 JAX_PROCESS_ID=2 {SIMULATE}", "must be below"),
        (f"FOJAX_UNION=maybe {SIMULATE}", "FOJAX_UNION"),
        (".venv/bin/fojax accuracy --horizon 0.5 --dt 0.1", "at least 1 s"),
        (".venv/bin/fojax bench --small --draws 4", "--small sets the sizes"),
        (".venv/bin/python -m experiments.bench_report --draws 0", "positive integer"),
        (".venv/bin/python -m pytest -q --no-such-option", "unrecognized arguments"),
        (".venv/bin/ruff check .", "installs no such program"),
    ],
)
def test_a_command_that_would_fail_is_named_with_the_reason(clone_view, line, reason):
    (command,) = commands_of(f"```bash\n{line}\n```\n", "doc.md")
    with pytest.raises(Rejected) as rejected:
        check(command, {})
    assert reason in str(rejected.value), (line, str(rejected.value))


def test_a_tuned_gains_file_exists_for_the_commands_after_the_tuning(clone_view):
    doc = clone_view / "doc.md"
    doc.write_text(f"```bash\n{TUNE}\n{SIMULATE.replace('r/s', 'r/u')} --gains "
                   "results/t/gains.json\n```\n")  # fmt: skip
    assert check_page(doc, clone_view) == []
    mismatch = clone_view / "other.md"
    mismatch.write_text(f"```bash\n{TUNE.replace('afonftsmc', 'fl').replace('/t', '/f')}\n"
                        f"{SIMULATE} --gains results/f/gains.json\n```\n")  # fmt: skip
    (problem,) = check_page(mismatch, clone_view)
    assert "holds gains of 'fl'" in problem


def test_a_law_of_ones_own_is_found_where_the_command_imports_from(clone_view, monkeypatch):
    """``fojax`` (a console script) does not import from the current folder, ``python -m``
    and ``PYTHONPATH=.`` do. A module name no other test uses, never imported before
    (tests/test_controllers.py imports a ``my_laws`` of its own into the same process)."""
    monkeypatch.delitem(sys.modules, "doc_check_laws", raising=False)
    (clone_view / "doc_check_laws.py").write_text("from fojax.controllers.fl import FL as Law\n")
    argv = "simulate --scenario 1 --controller doc_check_laws:Law --draws 4 --out results/law"
    (bare, with_path, module) = commands_of(
        f"```bash\n.venv/bin/fojax {argv}\nPYTHONPATH=. .venv/bin/fojax {argv}\n"
        f".venv/bin/python -m fojax.cli {argv}\n```\n",
        "doc.md",
    )
    with pytest.raises(Rejected, match="cannot import 'doc_check_laws'"):
        check(bare, {})
    check(with_path, {})
    check(module, {})
