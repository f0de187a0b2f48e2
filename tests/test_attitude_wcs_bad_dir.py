"""``hostlink attitude --wcs DIR`` where DIR is a file: a one-line error that says so (exit 2), not the operating
system's "File exists" from making a directory over it, given before anything is solved: no attitude file is
written and no success line printed."""

from hostlink.cli import main


def test_wcs_onto_a_file_says_a_file_is_there(tmp_path, capsys):
    assert main(["example", str(tmp_path)]) == 0
    session = tmp_path / "s.csv"
    camera = str(tmp_path / "true-camera.json")
    assert main(["simulate", "--camera", camera, "--frames", "3", "--out", str(session)]) == 0
    blocker = tmp_path / "wcs"
    blocker.write_text("not a directory")
    capsys.readouterr()
    code = main(["attitude", str(session), "--params", camera, "--out", str(tmp_path / "a.csv"), "--wcs", str(blocker)])
    said = capsys.readouterr()
    assert code == 2
    message = f"hostlink attitude: error: --wcs {blocker}: a file is there, not a directory"
    assert said.err.strip().splitlines() == [message]
    assert said.out == ""
    assert blocker.read_text() == "not a directory" and not (tmp_path / "a.csv").exists()
