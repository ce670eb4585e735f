"""`ctgs render`: user errors are one line and a non-zero exit (a full render of a finished run, and
failures part-way, are in tests/eval/test_stage_outputs.py)."""

from click.testing import CliRunner

from ctgs.cli import main


def test_render_missing_run_is_a_one_line_user_error(tmp_path):
    result = CliRunner().invoke(main, ["render", str(tmp_path / "nope"), "-o", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "run folder not found" in result.output and len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()  # nothing written before the inputs were checked
