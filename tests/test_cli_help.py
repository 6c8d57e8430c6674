"""Help texts speak to users and are complete (issue 17)."""
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
