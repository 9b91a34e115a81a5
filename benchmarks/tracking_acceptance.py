"""Tracking on simulated data with the real locator: the vortex ring and the fragment field.

Takes data sets written by ``plenoptrack simulate --scene vortex-ring`` and
``--scene fragments`` (each calibrated from its own white image and dot cards),
locates every frame with the default perspective-shift locator (flat-fielded), tracks, and
prints, against the truth:

- vortex ring: true links recovered (consecutive located detections of one true particle
  joined by one track), velocity RMS error over the mean true speed, depth error standard
  deviation (and robust 1.4826 MAD) per frame over track-smoothed, and how the depth
  error splits into a part each particle keeps along its track, a part shared with the
  other particles nearby (a field of the calibration's mapping) and the rest, which is
  all a smoother over time can average (:func:`depth_error_structure`);
- fragments: fragments of at least ``--min-diameter`` mm (volume-equivalent) visible in
  three or more frames (:func:`visible_frames`: the image centre inside the central view
  and the image not hidden inside others' in every view; whether or not the locator
  found them), how many of those one track holds completely (every frame in which the
  fragment was found: a located particle matched to it, or a track point matched to it
  where pieces were merged into one body, :mod:`plenoptrack.pieces`), the track's mean
  speed and median equivalent diameter against the truth (speed; ``sqrt(4 A / pi)`` of
  the projected area ``A``), tracked with order 1, a window of 6 frames and
  ``--fragment-memory`` (3, as in the README's fragment example).

Usage::

    python benchmarks/tracking_acceptance.py --vortex sim-vortex --fragments sim-frag \\
        --work acceptance-out
"""

from __future__ import annotations

import argparse
import json
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from plenoptrack.calibrate import calibrate
from plenoptrack.calibration import load_calibration, save_calibration
from plenoptrack.evaluate import evaluate_tracks, match_track_points
from plenoptrack.io import read_raw, read_table, write_table
from plenoptrack.lightfield import decode
from plenoptrack.locate.perspective import locate_frame
from plenoptrack.track import TrackSettings, track_particles


def _calibration(data: Path, work: Path):
    path = work / f"{data.name}_calib.json"
    if path.exists():
        return load_calibration(path)
    from plenoptrack.camera import load_camera

    t0 = time.perf_counter()
    calib, _report = calibrate(data / "white.tif", data / "dotcards", load_camera(data / "camera.toml"))
    save_calibration(calib, path)
    print(f"calibrated from {data} in {time.perf_counter() - t0:.1f} s")
    return calib


def _locate(data: Path, calib, out: Path, locator=None) -> pd.DataFrame:
    if out.exists():
        return read_table(out)
    white = decode(read_raw(data / "white.tif"), calib.grid)
    tables = []
    t0 = time.perf_counter()
    for f, path in enumerate(sorted((data / "raw").glob("frame_*.tif"))):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tables.append(locate_frame(read_raw(path), calib, frame=f, white=white,
                                       locator=locator).particles)
    particles = pd.concat(tables, ignore_index=True)
    write_table(particles, out)
    print(f"located {len(particles)} particles in {len(tables)} frames of {data} "
          f"in {time.perf_counter() - t0:.1f} s")
    return particles


def vortex(data: Path, calib, work: Path, tolerance: float) -> dict:
    particles = _locate(data, calib, work / "vortex_particles.parquet")
    truth = read_table(data / "truth.parquet")
    dt = tomllib.loads((data / "scene.toml").read_text())["frame_interval_s"]
    t0 = time.perf_counter()
    result = track_particles(particles, TrackSettings(frame_interval_s=dt))
    elapsed = time.perf_counter() - t0
    write_table(result.tracks, work / "vortex_tracks.parquet")
    ev = evaluate_tracks(result.tracks, truth, tolerance_mm=tolerance)
    n_true_frames = truth.groupby("frame").size()
    return {"true particles per frame": int(n_true_frames.iloc[0]),
            "frames": int(len(n_true_frames)), "located per frame": float(particles.groupby("frame").size().mean()),
            "tracks": len(result.statistics), "track time s": round(elapsed, 2),
            **ev.to_dict(),
            "velocity rms / mean speed": ev.velocity_rms_error / ev.mean_speed,
            "z sd ratio frame/smooth": ev.z_std_frame / ev.z_std_smooth,
            "z robust sd ratio frame/smooth": ev.z_rstd_frame / ev.z_rstd_smooth,
            "estimated depth scatter ratio": result.depth_scatter_ratio,
            "depth error structure": depth_error_structure(result.tracks, truth, tolerance)}


def _rstd(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(1.4826 * np.median(np.abs(a - np.median(a)))) if a.size else float("nan")


def depth_error_structure(tracks: pd.DataFrame, truth: pd.DataFrame, tolerance: float, *,
                          min_points: int = 8, radius_mm: float = 4.0) -> dict:
    """How much of the per-frame depth error a smoother over time could remove.

    Every tracked point is matched to its true particle; over the particles seen in at
    least ``min_points`` frames the depth error ``dz`` splits into each particle's median
    (kept along its track whatever the smoother does) and the rest (which it can average).
    The error shared in space is measured without the particle's own points: the median
    ``dz`` of the *other* particles' points within ``radius_mm`` predicts it (a field of the
    calibration's mapping, which every particle passing there carries). Returns robust
    (1.4826 MAD) spreads in mm, the lag-1 correlation of the rest within particles and
    the largest robust gain a perfect smoother of the rest could reach
    (``rstd(dz) / rstd(per-particle median)``).
    """
    from scipy.spatial import cKDTree

    ids = match_track_points(tracks, truth, tolerance_mm=tolerance).to_numpy()
    m = tracks[ids >= 0].assign(_true=ids[ids >= 0])
    true_xyz = truth.set_index(["frame", "particle"]).loc[
        list(zip(m["frame"], m["_true"])), ["x", "y", "z"]].to_numpy(float)
    m = m.assign(dz=m["z"].to_numpy(float) - true_xyz[:, 2])
    m = m[np.abs(m["dz"] - m["dz"].median()) < 10 * _rstd(m["dz"])]   # not the swapped points
    n = m.groupby("_true")["dz"].transform("size")
    m = m[n >= min_points].sort_values(["_true", "frame"])
    bias = m.groupby("_true")["dz"].transform("median")
    rest = (m["dz"] - bias).to_numpy()
    same = m["_true"].to_numpy()
    nxt = same[1:] == same[:-1]
    lag1 = float(np.corrcoef(rest[:-1][nxt], rest[1:][nxt])[0, 1])
    xyz = m[["x", "y", "z"]].to_numpy(float)
    dz = m["dz"].to_numpy(float)
    shared = np.full(len(m), np.nan)
    for i, near in enumerate(cKDTree(xyz).query_ball_point(xyz, radius_mm)):
        others = [j for j in near if same[j] != same[i]]
        if len(others) >= 3:
            shared[i] = np.median(dz[others])
    ok = np.isfinite(shared)
    per_particle = m.groupby("_true")["dz"].median().to_numpy()
    return {"particles": int(len(per_particle)), "points": int(len(m)),
            "dz robust sd, mm": _rstd(dz),
            "per-particle median dz, robust sd, mm": _rstd(per_particle),
            "within-particle dz, robust sd, mm": _rstd(rest),
            "within-particle lag-1 correlation": lag1,
            f"corr(dz, other particles' median dz within {radius_mm:g} mm)":
                float(np.corrcoef(dz[ok], shared[ok])[0, 1]),
            "dz less that shared part, robust sd, mm": _rstd(dz[ok] - shared[ok]),
            "largest robust gain of a smoother over time": _rstd(dz) / _rstd(per_particle)}


def visible_frames(truth: pd.DataFrame, calib, white) -> pd.Series:
    """Frames in which each true particle (index ``particle``) can be seen: its image
    centre lies inside the central view (``white``: the decoded white image) and the
    image is not hidden inside other particles' in every view the locator reads
    (:func:`plenoptrack.evaluate.hidden_particles`)."""
    from plenoptrack.evaluate import hidden_particles
    from plenoptrack.locate.perspective import MIN_VIEW_FRACTION

    u, v = np.meshgrid(white.u, white.v)
    views = np.c_[u[white.valid_fraction > MIN_VIEW_FRACTION],
                  v[white.valid_fraction > MIN_VIEW_FRACTION]]
    xyz = truth[["x", "y", "z"]].to_numpy(float)
    s, t = calib.dlfc.predict(*xyz.T, 0.0, 0.0)
    n_t, n_s = white.data.shape[2:]
    inside = (s >= 0) & (s <= n_s - 1) & (t >= 0) & (t <= n_t - 1)
    seen = inside & ~hidden_particles(truth, calib.dlfc, views)
    return truth[seen].groupby("particle").size()


def fragments(data: Path, calib, work: Path, tolerance: float, min_diameter: float,
              locator=None, memory: int = 3) -> dict:
    particles = _locate(data, calib, work / "fragment_particles.parquet", locator)
    truth = read_table(data / "truth.parquet")
    dt = tomllib.loads((data / "scene.toml").read_text())["frame_interval_s"]
    result = track_particles(particles, TrackSettings(order=1, window=6, search_range_mm=(1.5, 3.0),
                                                      frame_interval_s=dt, memory=memory))
    tracks = result.tracks
    write_table(tracks, work / "fragment_tracks.parquet")
    # every located row (before dropping short tracks) gets its true fragment
    located = particles.assign(_true=match_track_points(particles, truth, tolerance_mm=tolerance).to_numpy())
    tracks = tracks.assign(_true=match_track_points(tracks, truth, tolerance_mm=tolerance).to_numpy())
    first = truth[truth["frame"] == truth["frame"].min()].set_index("particle")
    speed = np.linalg.norm(first[["velocity_x", "velocity_y", "velocity_z"]].to_numpy(), axis=1)
    eq_d = np.sqrt(4 * first["projected_area"].to_numpy() / np.pi)
    info = pd.DataFrame({"diameter": first["diameter"].to_numpy(), "speed": speed, "eq_d": eq_d},
                        index=first.index)
    seen = located[located["_true"] >= 0].groupby("_true").size()
    # frames in which a fragment was found: located, or as the body of merged pieces
    # (plenoptrack.pieces), whose pieces lie too far from its centre to match alone
    found = (pd.concat([located[["_true", "frame"]], tracks[["_true", "frame"]]])
             .query("_true >= 0").drop_duplicates().groupby("_true").size())
    visible = visible_frames(truth, calib, decode(read_raw(data / "white.tif"), calib.grid))
    rows = []
    for pid, row in info.iterrows():
        n_seen = int(seen.get(pid, 0))
        n_found = int(found.get(pid, 0))
        mine = tracks[tracks["_true"] == pid]
        ids = mine["particle"].value_counts()
        best = int(ids.index[0]) if len(ids) else -1
        whole = len(ids) == 1 and ids.iloc[0] == n_found
        st = result.statistics.set_index("particle").loc[best] if best >= 0 else None
        rows.append({"particle": pid, "diameter": row["diameter"], "eq_d_true": row["eq_d"],
                     "visible": int(visible.get(pid, 0)), "seen": n_seen, "found": n_found,
                     "tracked_whole": bool(whole),
                     "points_in_best_track": int(ids.iloc[0]) if len(ids) else 0,
                     "speed_err": (st["speed"] / row["speed"] - 1) if st is not None else np.nan,
                     "eq_d_err": (st["diameter"] / row["eq_d"] - 1) if st is not None else np.nan})
    per = pd.DataFrame(rows)
    per.to_csv(work / "fragments_per_fragment.csv", index=False)
    big = per[(per["diameter"] >= min_diameter) & (per["visible"] >= 3)]
    return {"fragments": len(per),
            f"fragments >= {min_diameter} mm visible in >= 3 frames": len(big),
            "of those located in >= 3 frames": int((big["seen"] >= 3).sum()),
            "of those found in >= 3 frames (located, or merged from pieces)":
                int((big["found"] >= 3).sum()),
            "of those tracked whole": int(big["tracked_whole"].sum()),
            "of those found in >= 3 frames and tracked whole":
                int((big["tracked_whole"] & (big["found"] >= 3)).sum()),
            "speed error max |rel|": float(big["speed_err"].abs().max()),
            "speed error median |rel|": float(big["speed_err"].abs().median()),
            "eq. diameter error max |rel|": float(big["eq_d_err"].abs().max()),
            "eq. diameter error median |rel|": float(big["eq_d_err"].abs().median()),
            "eq. diameter within 10 %": int((big["eq_d_err"].abs() <= 0.10).sum()),
            "speed within 5 %": int((big["speed_err"].abs() <= 0.05).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vortex", type=Path)
    ap.add_argument("--fragments", type=Path)
    ap.add_argument("--calib-from", type=Path, help="data set whose white image and dot cards calibrate both (default: each its own)")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--tolerance", type=float, default=0.5,
                    help="matching tolerance, mm, laterally (three times that in depth)")
    ap.add_argument("--min-diameter", type=float, default=1.0)
    ap.add_argument("--fragment-settings", type=json.loads, default=None,
                    help="locator settings for the fragments as JSON, e.g. "
                         "'{\"segment\": {\"max_area_ratio\": 100, \"split_pairs\": false}}' "
                         "(sizes spanning a decade are not merged images)")
    ap.add_argument("--fragment-memory", type=int, default=3,
                    help="frames a fragment's track may miss (the README's fragment example: 3)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    report = {}
    if args.fragments:
        calib = _calibration(args.calib_from or args.fragments, args.work)
        locator = None
        if args.fragment_settings:
            from plenoptrack.locate.settings import PerspectiveLocator

            locator = PerspectiveLocator.from_dict(args.fragment_settings)
        report["fragments"] = fragments(args.fragments, calib, args.work, args.tolerance,
                                        args.min_diameter, locator, args.fragment_memory)
    if args.vortex:
        calib = _calibration(args.calib_from or args.vortex, args.work)
        report["vortex"] = vortex(args.vortex, calib, args.work, args.tolerance)
    print(json.dumps(report, indent=2, default=float))


if __name__ == "__main__":
    main()
