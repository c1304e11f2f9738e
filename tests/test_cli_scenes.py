"""The scene and episode commands, including their errors on bad input (exit code 2, no traceback)."""

from __future__ import annotations

import pytest

from mapless.cli import main


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_list_and_targets(capsys):
    code, out, _ = run(capsys, "scenes", "list", "test:bathroom")
    assert code == 0 and out.count("FloorPlan4") == 5 and "bathroom" in out
    code, out, _ = run(capsys, "scenes", "targets")
    assert code == 0 and "Vase" in out and "12/20" in out  # Vase is in 12 of 20 training living rooms


def test_check_reports_components_and_never_visible_targets(capsys):
    code, out, _ = run(capsys, "scenes", "check", "FloorPlan427", "--protocols", "standard")
    row = next(line for line in out.splitlines() if line.startswith("FloorPlan427"))
    assert code == 0 and "896+32" in row.split()  # a 32-pose island beside the usable component
    assert "Target instances no pose can see under the standard protocol (success within 1.0 m)" in out


def test_show_writes_a_png(tmp_path, capsys):
    out_file = tmp_path / "scene.png"
    code, _, _ = run(capsys, "scenes", "show", "FloorPlan425", "--pose=-1.25,1.75,90,30", "--target", "Towel",
                     "--out", str(out_file))  # fmt: skip
    assert code == 0 and out_file.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (("scenes", "show", "FloorPlan999", "--out", "x.png"), "unknown scene 'FloorPlan999'"),
        (("scenes", "show", "FloorPlan1", "--target", "Toastr", "--out", "x.png"), "Did you mean Toaster"),
        (("scenes", "show", "FloorPlan425", "--pose", "0.1,0.1,0,0", "--out", "x.png"), "nearest valid pose"),
        (
            ("scenes", "build", "FloorPlan1", "--sim", "visiblity_distance=1"),
            "unknown config key 'visiblity_distance'",
        ),
        (
            ("scenes", "build", "FloorPlan1", "--sim", "visibility_distance=far"),
            "config key 'visibility_distance'",
        ),
        (("scenes", "list", "tset"), "unknown split 'tset'"),
        (("episodes", "show", "nowhere"), "neither an episode file nor"),
        (
            ("episodes", "show", "test", "--index", "1000", "--out", "x.png"),
            "--index 1000: the set has episodes 0 to 999",
        ),
        (
            ("episodes", "show", "test", "--index", "-1", "--out", "x.png"),
            "--index -1: the set has episodes 0 to 999",
        ),
        (("interop", "episodes-export", "nowhere", "--out", "x"), "neither an episode file nor"),
    ],
)
def test_bad_input_is_a_clean_error(capsys, argv, message):
    code, _, err = run(capsys, *argv)
    assert code == 2
    assert message in err and "Traceback" not in err


def test_episodes_show_summarises_a_builtin_set(capsys):
    code, out, _ = run(capsys, "episodes", "show", "test")
    assert code == 0 and "1000 episodes" in out and out.count("250 eps") == 4
