"""Help texts speak to users and are complete."""
import pytest

from tlvg_warp.cli import main


def _help(capsys, *argv):
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_top_level_help_is_whole_and_starts_the_user(capsys):
    text = _help(capsys)
    assert "tlvg_warp/commands" not in text and "add_arguments" not in text  # no developer notes
    assert "python -m tlvg_warp stylize" in text and "demo" in text and "COMMAND --help" in text


def test_stylize_help_says_no_arguments_is_the_demo(capsys):
    assert "With no arguments: the built-in demo" in _help(capsys, "stylize")


def test_bench_help_says_its_default(capsys):
    assert "sweep (the default)" in _help(capsys, "bench")


def test_bad_flag_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        main(["bench", "--repeats", "many"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--repeats" in err[0]


# --- --help, the README and docs/commands.md agree on every flag --------------------------------------------------
import argparse  # noqa: E402
import importlib  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _commands() -> dict:
    """{command: its parser's flags}, built as the CLI builds them (commands whose module is absent are left out)."""
    from tlvg_warp.cli import COMMANDS

    out = {}
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"tlvg_warp.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"tlvg_warp.commands.{name}":
                raise
            continue
        p = argparse.ArgumentParser(prog=name)
        mod.add_arguments(p)
        out[name] = {s for a in p._actions for s in a.option_strings if s.startswith("--")} - {"--help"}
    return out


def _help_flags(capsys, name) -> set:
    with pytest.raises(SystemExit):
        main([name, "--help"])
    return set(FLAG.findall(capsys.readouterr().out)) - {"--help"}


def _reference() -> dict:
    """docs/commands.md: {command: the flags in the first column of its table}."""
    text = (REPO / "docs" / "commands.md").read_text()
    out = {}
    for part in re.split(r"^## ", text, flags=re.M)[1:]:
        name, body = part.split("\n", 1)
        rows = [ln.split("|")[1] for ln in body.splitlines() if ln.startswith("| `")]
        out[name.strip()] = {f for r in rows for f in FLAG.findall(r)}
    return out


def test_docs_reference_lists_every_flag_of_every_command_and_no_other(capsys):
    """Both ways: a flag added to a command and not documented fails, so does a documented flag that is gone.
    The parsers' flags are checked against the --help text too (what a user reads)."""
    ref, cmds = _reference(), _commands()
    assert set(ref) == set(cmds), f"commands without a section: {set(cmds) - set(ref)}, stale: {set(ref) - set(cmds)}"
    for name, flags in cmds.items():
        assert _help_flags(capsys, name) >= flags, name
        assert ref[name] == flags, (f"{name}: undocumented {sorted(flags - ref[name])}, "
                                    f"documented but not accepted {sorted(ref[name] - flags)}")


def test_every_flag_the_readme_and_docs_show_is_accepted():
    """Each `python -m tlvg_warp COMMAND ...` in README.md and docs/*.md: the flags written after the command (to
    the end of its code span or line) are flags of that command."""
    cmds = _commands()
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for m in re.finditer(r"python -m tlvg_warp (\w+)([^`\n]*)", doc.read_text()):
            name, rest = m.group(1), m.group(2).split("&&")[0]
            if name not in cmds:
                continue
            unknown = set(FLAG.findall(rest)) - cmds[name] - {"--help"}
            assert not unknown, f"{doc.name}: `{m.group(0).strip()}` shows {sorted(unknown)}, not flags of {name}"


def test_vgg_weights_help_names_every_accepted_value(capsys):
    """load_vgg takes a path, 'hed' and 'random'; every command with --vgg-weights says so."""
    for name, flags in _commands().items():
        if "--vgg-weights" in flags:
            with pytest.raises(SystemExit):
                main([name, "--help"])
            text = " ".join(capsys.readouterr().out.split())
            i = text.rindex("--vgg-weights")  # its entry under options (not the usage line)
            assert "hed" in text[i:i + 300] and "random" in text[i:i + 300], name


def test_skip_messages_name_the_extra_the_readme_names():
    """An optional test dependency is named by its extra in pyproject.toml and the skip message."""
    text = (REPO / "tests" / "test_io_splat_formats.py").read_text()
    assert "pip install -e '.[interop]'" in text and "pip install gsply" not in text
    assert re.search(r"^interop = \[.*gsply", (REPO / "pyproject.toml").read_text(), re.M)


def test_building_the_parser_loads_no_heavy_library():
    """cli.py imports every command to build its parser, so the commands import what they run inside their
    functions: --help (and a bad flag) load neither Warp nor OpenCV, matplotlib or YAML."""
    import os
    import subprocess
    import sys

    code = ("import sys\nfrom tlvg_warp.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('warp', 'cv2', 'matplotlib', 'yaml', 'tlvg_warp.losses', 'tlvg_warp.stylize')"
            " if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, cwd=REPO)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "[]"
