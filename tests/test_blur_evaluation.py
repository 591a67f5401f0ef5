"""Motion-blurred synthetic sequences: the synth command's options, and the evaluation against their sharp frames."""

import numpy as np
from click.testing import CliRunner

from cli import main
from tambridge.io.synthetic import RotationBursts, SynthOptions
from tambridge.io.tum import GT_RGB_FOLDER
from tambridge.trajectory import read_tum_trajectory


def test_synth_command_takes_the_exposure_in_seconds_and_bursts(tmp_path):
    out = tmp_path / "blurred"
    result = CliRunner().invoke(main, ["synth", str(out), "--frames", "30", "--size", "32x24", "--motion-blur", "0.02",
                                       "--blur-subframes", "2", "--rotation-bursts", "1", "--burst-duration", "0.5"])
    assert result.exit_code == 0, result.output
    assert len(list((out / GT_RGB_FOLDER).iterdir())) == len(list((out / "rgb").iterdir())) == 30
    expected = SynthOptions(30, 32, 24, exposure_s=0.02, bursts=RotationBursts(1, duration_s=0.5)).path.poses(np.arange(30))
    np.testing.assert_allclose(read_tum_trajectory(out / "groundtruth.txt").world_from_camera, expected, atol=1e-6)
    refused = CliRunner().invoke(main, ["synth", str(tmp_path / "no"), "--frames", "30", "--rotation-bursts", "2"])
    assert refused.exit_code != 0 and "do not fit" in refused.output and not (tmp_path / "no").exists()
