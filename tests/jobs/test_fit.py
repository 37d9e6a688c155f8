"""``usplat fit`` (``usplat_dr.jobs.fit``): the command around
``usplat_dr.training.per_scene`` (tested in tests/training/test_per_scene.py)."""

import pytest


def test_cli_fit_writes_png_and_json(tmp_path, capsys):
    from usplat_dr.cli import main
    from usplat_dr.data.synth import synthesize

    synthesize(tmp_path / "set", scenes=1, frames=5, resolution=(12, 12), spp=2, progress=False)
    assert main(["-q", "fit", "--data", str(tmp_path / "set"), "--iterations", "2",
                 "--out", str(tmp_path / "fit")]) == 0
    assert "held-out PSNR" in capsys.readouterr().out
    assert (tmp_path / "fit" / "fit_indoor_0_00000.png").is_file()
    assert (tmp_path / "fit" / "fit_indoor_0_00000.json").is_file()
    with pytest.raises(SystemExit, match="not in"):
        main(["-q", "fit", "--data", str(tmp_path / "set"), "--scene", "nope", "--iterations",
              "1", "--out", str(tmp_path / "fit")])
    with pytest.raises(SystemExit):
        main(["fit", "--iterations", "0"])
