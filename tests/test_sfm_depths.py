"""data/sfm_tracks.train_observation_depths through the dataparser: each training photo's SfM observations carry
their point's depth in the scene's own (transformed, scaled) frame, the frame the renders' expected depth is in."""

from pathlib import Path

import numpy as np

from willags_ns.data.colmap import find_colmap_model, read_colmap_model
from willags_ns.data.dataparser import WillagsDataParserConfig
from willags_ns.data.sfm_tracks import SFM_DEPTHS_KEY, SFM_OBSERVATIONS_KEY


def test_a_photos_sfm_depths_are_its_points_depths_along_its_own_camera_in_the_scenes_frame(shared_data):
    scene = shared_data / "sacre-coeur-mini"
    parser = WillagsDataParserConfig(data=scene).setup()
    out = parser.get_dataparser_outputs("train")
    obs, depths = out.metadata[SFM_OBSERVATIONS_KEY], out.metadata[SFM_DEPTHS_KEY]()  # read when asked
    assert len(depths) == len(obs) == len(out.image_filenames)
    colmap = read_colmap_model(find_colmap_model(scene), points=True)
    by_name = {im.name: im for im in colmap.images.values()}
    t, s = out.dataparser_transform.numpy(), float(out.dataparser_scale)
    for i in (0, len(obs) - 1):
        assert depths[i].shape == (obs[i].shape[0],) and obs[i].shape[0] > 100
        im = by_name[Path(out.image_filenames[i]).name]
        ids = np.asarray(im.point3D_ids).reshape(-1)
        xyz = np.stack([colmap.points[int(j)].xyz for j in ids[ids >= 0]])
        in_scene = s * (xyz @ t[:3, :3].T + t[:3, 3])  # the points where the Gaussians and cameras live
        c2w = out.cameras.camera_to_worlds[i].numpy()
        cam = (in_scene - c2w[:, 3]) @ c2w[:, :3]  # OpenGL camera: looking along -z
        assert np.allclose(depths[i], -cam[:, 2], rtol=1e-4)
        # and the observations are where those points project (pixel centres, normalised)
        u = (float(out.cameras.fx[i]) * cam[:, 0] / -cam[:, 2] + float(out.cameras.cx[i])) / int(out.cameras.width[i])
        assert np.median(np.abs(u - obs[i][:, 0])) < 2e-3
