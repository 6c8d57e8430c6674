"""`bench raster --scene`: a fitted scene timed over its views (a CPU smoke run), with list-length statistics that
must equal a direct brute-force computation."""
import json
import math

import numpy as np
import pytest
import torch

from tlvg_warp.eval import bench_raster as br
from tlvg_warp.io.ply import save_ply
from tlvg_warp.kernels.blend import ALPHA_MAX, ALPHA_MIN, T_MIN
from tlvg_warp.raster import capture_binning

from _io_helpers import write_png
from test_raster import fitted_like_scene, reference_tile_pairs


def tiny_blender_dataset(root, cams_c2w, width=64, height=48, fov_x=0.9):
    frames = []
    for k, c2w in enumerate(cams_c2w):
        write_png(root / f"r_{k}.png", np.full((height, width, 3), 128, np.uint8))
        frames.append({"file_path": f"./r_{k}", "transform_matrix": c2w.tolist()})
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}))


def look_from(eye):
    """camera-to-world in OpenGL axes (Blender's convention) looking at the origin, z up."""
    eye = np.asarray(eye, np.float64)
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def direct_lists(g, cam):
    """The list lengths of one view by brute force: the binning criterion per (Gaussian, tile) in float64, each
    tile's list in depth order, and each pixel's walk (float32 alpha, as the kernel) to its last contributor."""
    with capture_binning() as cap, torch.no_grad():
        br.render(g, cam, depth=False)
    proj = cap["proj"]  # our projection: only the binning and blending walk are checked here
    member, _ = reference_tile_pairs(proj, cam.width, cam.height)  # [N, tiles]
    per_tile = member.sum(0)
    m, q, o, depth = proj.means2d.float(), proj.conic.float(), proj.opacity.float(), proj.depth.float()
    tiles_x = math.ceil(cam.width / 16)
    walked = torch.zeros(cam.height, cam.width, dtype=torch.long)
    for t in range(member.shape[1]):
        ids = member[:, t].nonzero().flatten()
        ids = ids[torch.argsort(depth[ids], stable=True)]  # ties by index, as the stable radix sort
        ty, tx = divmod(t, tiles_x)
        ys = torch.arange(ty * 16, min(ty * 16 + 16, cam.height))
        xs = torch.arange(tx * 16, min(tx * 16 + 16, cam.width))
        py, px = torch.meshgrid(ys.float() + 0.5, xs.float() + 0.5, indexing="ij")
        dx, dy = px.reshape(-1, 1) - m[ids, 0], py.reshape(-1, 1) - m[ids, 1]
        power = -0.5 * (q[ids, 0] * dx * dx + q[ids, 2] * dy * dy) - q[ids, 1] * dx * dy
        alpha = torch.clamp_max(o[ids] * torch.exp(power), ALPHA_MAX)
        valid = (power <= 0) & (alpha >= ALPHA_MIN)
        a = torch.where(valid, alpha, torch.zeros_like(alpha))
        stop = torch.cumsum(valid & (torch.cumprod(1 - a, 1) < T_MIN), 1) > 0
        contrib = valid & ~stop
        pos = torch.arange(1, len(ids) + 1)
        last = (contrib * pos).amax(1) if len(ids) else torch.zeros(len(ys) * len(xs), dtype=torch.long)
        walked[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1] = last.reshape(len(ys), len(xs))
    return {"intersections": int(per_tile.sum()), "tile_mean": per_tile.double().mean().item(),
            "tile_max": int(per_tile.max()), "px_mean": walked.double().mean().item(), "px_max": int(walked.max())}


def test_scene_case_over_dataset_views_reports_the_true_list_lengths(tmp_path):
    g = fitted_like_scene(n_small=300, seed=4)
    save_ply(g, tmp_path / "point_cloud.ply")
    tiny_blender_dataset(tmp_path / "data", [look_from((0.3, -3.0, 0.4)), look_from((2.4, -1.8, 0.6))])
    case = br.scene_case(f"{tmp_path / 'point_cloud.ply'}:{tmp_path / 'data'}", torch.device("cpu"))
    assert len(case.cams) == 2 and (case.cams[0].width, case.cams[0].height) == (64, 48)
    rows = br.run_bench([case], torch.device("cpu"), repeats=1, peers=("tlvg_warp",), log=lambda r: None)
    (row,) = rows
    assert row["views"] == 2 and len(row["per_view_fwd_ms"]) == 2 and row["fwd_bwd_ms"] > 0
    per_view = [direct_lists(case.g, cam) for cam in case.cams]
    got = row["lists"]
    assert got["intersections"] == statistics_mean([v["intersections"] for v in per_view])
    assert got["intersections_max"] == max(v["intersections"] for v in per_view)
    assert got["tile_max"] == max(v["tile_max"] for v in per_view)
    assert got["px_max"] == max(v["px_max"] for v in per_view)
    assert abs(got["tile_mean"] - statistics_mean([v["tile_mean"] for v in per_view])) < 1e-9
    assert abs(got["px_mean"] - statistics_mean([v["px_mean"] for v in per_view])) < 1e-9
    assert got["tile_max"] > 2 * got["tile_mean"] > 0 and got["px_max"] > 0  # long lists where the big ones are
    table = br.format_table(rows)
    assert f"{got['tile_mean']:.0f} / {got['tile_max']}" in table


def test_scene_without_dataset_gets_orbit_views_and_the_cli_runs(tmp_path, capsys):
    from tlvg_warp.cli import main

    g = fitted_like_scene(n_small=200, seed=5)
    save_ply(g, tmp_path / "s.ply")
    case = br.scene_case(str(tmp_path / "s.ply"), torch.device("cpu"), max_views=3, orbit_size=(40, 30))
    assert len(case.cams) == 3 and all(c.width == 40 for c in case.cams)
    with torch.no_grad():
        assert all(br.render(case.g, c, depth=False).alpha.max() > 0.5 for c in case.cams)  # the scene is in view
    main(["bench", "raster", "--device", "cpu", "--quick", "--sizes", "300", "--size", "40x30", "--garden", "",
          "--peers", "tlvg_warp", "--repeats", "1", "--scene", str(tmp_path / "s.ply"), "--views", "2",
          "--out", str(tmp_path / "out")])
    res = json.loads((tmp_path / "out" / "bench_raster.json").read_text())
    random_row, row = res["rows"]
    assert random_row["n"] == 300 and random_row["size"] == "40x30" == row["size"]  # --size reaches both cases
    assert row["views"] == 2 and row["lists"]["tile_max"] > 0 and not res["ours_depth"]
    assert "orbit 2 views" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["bench", "raster", "--size", "40x"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--size" in err[0] and "'40x'" in err[0]


def test_kernel_names_map_to_stages():
    names = {"emit_keys_kernel_4d1184f3_cuda_kernel_forward": "bin",
             "void gsplat::intersect_tile_kernel<float>(bool, unsigned int": "bin",
             "make_blend__locals__blend_forward_kernel_b435ef08_cuda_kernel_forward": "blend fwd",
             "void gsplat::rasterize_to_pixels_3dgs_bwd_kernel<3u, float>(": "blend bwd",
             "void cub::CUB_300001_SM_900::detail::radix_sort::DeviceRadixSortOnesweepKernel": "sort",
             "make_sh__locals__sh_coeff_grad_kernel_ba2bb44d_cuda_kernel_forward": "sh",
             "make_projection__locals__project_kernel_99a15968_cuda_kernel_backward": "project",
             "Memset (Device)": "other"}
    assert {k: br.stage_of(k) for k in names} == names
    assert br.format_stages([{"case": "c", "peer": "p", "fwd_ms": 1.0, "stages_fwd": {"bin": 0.5, "gpu total": 0.7}}]) \
        .splitlines()[2].startswith("| c | p | fwd | - | - | 0.500 |")


def statistics_mean(xs):
    return sum(xs) / len(xs)
