"""The nuScenes v1.0 writer: ROOT/<version>/ with the 13 tables (attribute, calibrated_sensor,
category, ego_pose, instance, log, map, sample, sample_annotation, sample_data, scene, sensor,
visibility), lidarseg.json and image_annotations.json (per camera and keyframe the tight 2D
box of each annotated actor's pixels, the devkit's 2D table); an instance row also names the
actor's prim (``prim``); ROOT/samples/<channel>/ (keyframes) and ROOT/sweeps/<channel>/
(the frames between) with nuScenes' file names; ROOT/lidarseg/<version>/<token>_lidarseg.bin
(uint8 category index per point of each keyframe sweep); ROOT/maps/<token>.png (drivable area,
datasets.maps). One nuScenes scene and log per route.

Units and frames as nuScenes has them: metres, quaternions w x y z, poses parent-from-child
(ego_pose: global-from-ego, calibrated_sensor: ego-from-sensor; cameras in OpenCV axes),
sizes width, length, height, timestamps in microseconds. The global frame is the scene's world
shifted to the map's origin (datasets.maps). A .pcd.bin holds float32 x, y, z, intensity
(0-255: our [0, 1] model intensity x 255), ring per point, in the LiDAR frame at the sweep's
timestamp (its start; the sweep is motion-compensated to it).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.datasets import mapping as M
from lsd3d_usd.datasets.maps import mask_image, write_mask
from lsd3d_usd.datasets.tokens import timestamp_us, token
from lsd3d_usd.datasets.writers import encode_image, quat_wxyz, write_bytes

TABLES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map",
          "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility")


class NuScenesWriter:
    name = "nuscenes"
    # what --overwrite may delete (relative to the dataset folder; ``{version}`` filled in)
    files = ("{version}/*.json", "samples/*/*", "sweeps/*/*", "maps/*.png",
             "lidarseg/{version}/*.bin")
    # a log record's shape, checked before the tables are merged (datasets.build.record_problem)
    record_shape = {**{t: [dict] for t in ("calibrated_sensor", "ego_pose", "sample",
                                           "sample_annotation", "sample_data", "instance",
                                           "scene", "lidarseg", "image_annotations")},
                    "log": [{"token": str}], "map": [{"token": str}], "channels": {str: str}}

    def __init__(self, root: Path, options):
        self.root = Path(root)
        self.version = options.version
        self.opt = options

    # ---------------------------------------------------------------- per log
    def begin_log(self, info) -> None:
        self.info = info
        p = info.plan
        self.key = (self.version, p.key)
        self.log_name = f"lsd3d-{p.index:04d}-{p.scene_name}"
        self.rows = {t: [] for t in ("calibrated_sensor", "ego_pose", "sample",
                                     "sample_annotation", "sample_data", "lidarseg",
                                     "image_annotations")}
        self.keyframe_sd = {}        # channel -> sample_data row of the current keyframe
        self.instances = {}          # prim -> instance row (with its category)
        self.last_ann = {}           # prim -> its last annotation row
        self.last_sd = {}            # channel -> its last sample_data row
        self.last_sample = None
        self._sent = {}              # table -> rows already in a checkpoint
        self.n_keyframes = info.timeline.counts()["keyframes"]
        self.kf_hz = float(info.timeline.keyframe_hz)
        # the map and the global frame
        self.origin = np.zeros(3)
        self.map_row = None
        if info.layout is not None:
            mask, self.origin = mask_image(info.layout)
            mtok = token(self.version, p.scene_name, "map")
            fname = f"maps/{mtok}.png"
            if not (self.root / fname).exists() or not self.opt.resume:
                write_mask(self.root / fname, mask)
            self.map_row = {"token": mtok, "log_tokens": [], "category": "semantic_prior",
                            "filename": fname}
        self.log_token = token(*self.key, "log")
        self.calib = {}
        for c in info.cameras:
            self.calib[c.name] = self._calibrated(c.name, info.ego_from_camera[c.name], None)
        if info.lidar is not None:
            self.calib["LIDAR_TOP"] = self._calibrated("LIDAR_TOP", info.ego_from_lidar, [])
        self.lidarseg_table, self.lidarseg_inst = M.lidarseg_table(info.instances.rows)

    def _calibrated(self, channel, ego_from_sensor, intrinsic):
        tok = token(*self.key, "calibrated_sensor", channel)
        row = {"token": tok, "sensor_token": token("sensor", channel),
               "translation": np.asarray(ego_from_sensor)[:3, 3].tolist(),
               "rotation": quat_wxyz(ego_from_sensor),
               "camera_intrinsic": intrinsic if intrinsic is not None else []}
        self.rows["calibrated_sensor"].append(row)
        return row

    def _ts(self, seconds: float) -> int:
        return timestamp_us(self.info.plan.index, seconds)

    def _sample_token(self, k: int) -> str:
        return token(*self.key, "sample", self._ts(k / self.kf_hz))

    def _nearest_sample(self, t: float) -> str:
        k = int(np.clip(np.floor(t * self.kf_hz + 0.5 - 1e-9), 0, self.n_keyframes - 1))
        return self._sample_token(k)

    def _global(self, M4):
        G = np.array(M4, np.float64)
        G[:3, 3] -= self.origin
        return G

    # ---------------------------------------------------------------- per sample
    def write(self, s) -> None:
        ts = self._ts(s.time)
        if s.keyframe:
            tok = self._sample_token(s.tick.keyframe_index)
            row = {"token": tok, "timestamp": ts, "prev": "", "next": "",
                   "scene_token": token(*self.key, "scene")}
            if self.last_sample is not None:
                row["prev"] = self.last_sample["token"]
                self.last_sample["next"] = tok
            self.rows["sample"].append(row)
            self.last_sample = row
        for shot in s.cameras:
            h, w = shot.image.shape[:2]
            if self.calib[shot.channel]["camera_intrinsic"] == []:
                self.calib[shot.channel]["camera_intrinsic"] = shot.K.tolist()
            self._sample_data(s, shot.channel, ts, "jpg", encode_image(shot.image, "jpg"), w, h)
        if s.lidar is not None:
            sw = s.lidar.sweep
            pts = np.empty((len(sw.range), 5), np.float32)
            pts[:, :3] = sw.xyz
            pts[:, 3] = np.clip(sw.intensity * 255.0, 0, 255)
            pts[:, 4] = sw.ring
            sd = self._sample_data(s, "LIDAR_TOP", ts, "pcd", pts.tobytes(), 0, 0,
                                   ext="pcd.bin")
            if s.keyframe:
                labels = M.point_labels(sw.class_id, sw.instance_id, self.lidarseg_table,
                                        self.lidarseg_inst)
                fname = f"lidarseg/{self.version}/{sd['token']}_lidarseg.bin"
                write_bytes(self.root / fname, labels.tobytes())
                self.rows["lidarseg"].append({"token": sd["token"],
                                              "sample_data_token": sd["token"],
                                              "filename": fname})
        if s.keyframe:
            self._annotations(s, ts)

    def _sample_data(self, s, channel, ts, fileformat, data, w, h, ext=None):
        folder = "samples" if s.keyframe else "sweeps"
        fname = f"{folder}/{channel}/{self.log_name}__{channel}__{ts}.{ext or fileformat}"
        write_bytes(self.root / fname, data)
        tok = token(*self.key, "sample_data", channel, ts)
        ego_tok = token(*self.key, "ego_pose", channel, ts)
        G = self._global(s.world_from_ego)
        self.rows["ego_pose"].append({"token": ego_tok, "timestamp": ts,
                                      "rotation": quat_wxyz(G), "translation": G[:3, 3].tolist()})
        row = {"token": tok, "sample_token": self._sample_token(s.tick.keyframe_index)
               if s.keyframe else self._nearest_sample(s.time),
               "ego_pose_token": ego_tok, "calibrated_sensor_token": self.calib[channel]["token"],
               "timestamp": ts, "fileformat": fileformat, "is_key_frame": bool(s.keyframe),
               "height": int(h), "width": int(w), "filename": fname, "prev": "", "next": ""}
        last = self.last_sd.get(channel)
        if last is not None:
            row["prev"] = last["token"]
            last["next"] = tok
        self.last_sd[channel] = row
        self.rows["sample_data"].append(row)
        if s.keyframe:
            self.keyframe_sd[channel] = row
        return row

    def _annotations(self, s, ts) -> None:
        stok = self._sample_token(s.tick.keyframe_index)
        for b in s.boxes:
            n_lidar = b.num_lidar_pts or 0
            if n_lidar <= 0 and (b.pixels or 0) <= 0:
                continue            # nothing of it sensed: not annotated (as nuScenes)
            cat = M.actor_category(b.label, b.kind)
            inst = self.instances.get(b.prim)
            if inst is None:
                inst = self.instances[b.prim] = {
                    "token": token(*self.key, "instance", b.prim),
                    "category_token": token("category", cat), "nbr_annotations": 0,
                    "first_annotation_token": "", "last_annotation_token": "",
                    "prim": b.prim}
            atok = token(*self.key, "sample_annotation", b.prim, ts)
            attr = M.attribute(cat, b.role, b.speed())
            from scipy.spatial.transform import Rotation
            R = Rotation.from_quat(b.rotation_xyzw).as_matrix()
            L_, W_, H_ = b.size
            row = {"token": atok, "sample_token": stok, "instance_token": inst["token"],
                   "visibility_token": M.visibility_token(b.visible_fraction or 0.0),
                   "attribute_tokens": [token("attribute", attr)] if attr else [],
                   "translation": (np.asarray(b.center) - self.origin).tolist(),
                   "size": [W_, L_, H_], "rotation": quat_wxyz(R), "prev": "", "next": "",
                   "num_lidar_pts": int(n_lidar), "num_radar_pts": 0}
            last = self.last_ann.get(b.prim)
            if last is not None:
                row["prev"] = last["token"]
                last["next"] = atok
            else:
                inst["first_annotation_token"] = atok
            inst["last_annotation_token"] = atok
            inst["nbr_annotations"] += 1
            self.last_ann[b.prim] = row
            self.rows["sample_annotation"].append(row)
            self._image_annotations(b, row, cat)

    def _image_annotations(self, b, ann, cat) -> None:
        """2D boxes per camera (image_annotations.json, the devkit's 2D table): the tight box
        of the actor's instance pixels, with its visible fraction in that camera."""
        for channel, e in sorted(b.cameras.items()):
            if e.box_2d is None or channel not in self.keyframe_sd:
                continue
            sd = self.keyframe_sd[channel]
            self.rows["image_annotations"].append({
                "sample_annotation_token": ann["token"], "sample_data_token": sd["token"],
                "instance_token": ann["instance_token"], "category_name": cat,
                "attribute_tokens": ann["attribute_tokens"],
                "visibility_token": ann["visibility_token"], "filename": sd["filename"],
                "bbox_corners": [float(v) for v in e.box_2d],
                "num_lidar_pts": ann["num_lidar_pts"], "num_radar_pts": 0,
                "visible_fraction": float(e.visible_fraction), "pixels": int(e.pixels),
                "truncated": float(e.truncated),
                "prev": "", "next": ""})

    # ---------------------------------------------------------------- resuming
    # A checkpoint is the rows added since the previous one (and the instances first seen):
    # append-only, so its cost is what the keyframe added. The fields a later row changes
    # (a row's ``next``, an instance's count and first / last annotation) are not journaled
    # but derived again in ``restore``. The calibrated_sensor rows go in the first delta,
    # complete: every sensor fires at keyframe 0 (tick 0), setting the cameras' intrinsics.
    LINKED = ("sample", "sample_data", "sample_annotation")

    def checkpoint(self) -> dict:
        """The log's rows since the previous checkpoint (JSON-able; ``restore`` takes them)."""
        sent = self._sent
        delta = {t: rows[sent.get(t, 0):] for t, rows in self.rows.items()}
        inst = list(self.instances.values())
        delta["instance"] = inst[sent.get("instance", 0):]
        self._sent = {**{t: len(rows) for t, rows in self.rows.items()}, "instance": len(inst)}
        return delta

    def restore(self, info, deltas: list) -> None:
        self.begin_log(info)
        self.rows = {t: [r for d in deltas for r in d[t]] for t in self.rows}
        for t in self.LINKED:
            by_tok = {r["token"]: r for r in self.rows[t]}
            for r in self.rows[t]:
                r["next"] = ""
                if r["prev"]:
                    by_tok[r["prev"]]["next"] = r["token"]
        insts = [i for d in deltas for i in d["instance"]]
        by_inst = {}
        for i in insts:
            i.update(nbr_annotations=0, first_annotation_token="", last_annotation_token="")
            by_inst[i["token"]] = i
        for a in self.rows["sample_annotation"]:
            i = by_inst[a["instance_token"]]
            i["nbr_annotations"] += 1
            i["first_annotation_token"] = i["first_annotation_token"] or a["token"]
            i["last_annotation_token"] = a["token"]
        self.instances = {i["prim"]: i for i in insts}
        self._sent = {**{t: len(rows) for t, rows in self.rows.items()}, "instance": len(insts)}
        cs = {r["token"]: r for r in self.rows["calibrated_sensor"]}
        self.calib = {c: cs[r["token"]] for c, r in self.calib.items()}
        self.last_sample = self.rows["sample"][-1] if self.rows["sample"] else None
        self.last_sd = {}
        for r in self.rows["sample_data"]:
            self.last_sd[r["filename"].split("/")[1]] = r
        ann = {r["token"]: r for r in self.rows["sample_annotation"]}
        self.last_ann = {prim: ann[i["last_annotation_token"]]
                         for prim, i in self.instances.items()}

    def end_log(self) -> dict:
        p = self.info.plan
        samples = self.rows["sample"]
        scene = {"token": token(*self.key, "scene"), "log_token": self.log_token,
                 "nbr_samples": len(samples),
                 "first_sample_token": samples[0]["token"] if samples else "",
                 "last_sample_token": samples[-1]["token"] if samples else "",
                 "name": f"scene-{p.index:04d}",
                 "description": f"lsd3d-usd {p.scene_name}, route {','.join(p.route)}, "
                                f"rig {self.info.rig}"}
        log = {"token": self.log_token, "logfile": self.log_name, "vehicle": "lsd3d-ego",
               "date_captured": "2026-01-01", "location": p.scene_name}
        return {**self.rows, "instance": list(self.instances.values()), "scene": [scene],
                "log": [log], "map": [self.map_row] if self.map_row else [],
                "channels": {c: ("camera" if c != "LIDAR_TOP" else "lidar") for c in self.calib}}

    # ---------------------------------------------------------------- the tables
    def finish(self, records: list) -> dict:
        tables = {t: [] for t in TABLES}
        tables["category"] = [{"token": token("category", n), "name": n, "description": d,
                               "index": i} for i, (n, d) in enumerate(M.CATEGORIES)]
        tables["attribute"] = [{"token": token("attribute", n), "name": n, "description": d}
                               for n, d in M.ATTRIBUTES]
        tables["visibility"] = [{"token": t, "level": lv, "description": d}
                                for t, lv, d in M.VISIBILITY]
        channels, maps, lidarseg, image_anns = {}, {}, [], []
        for rec in records:
            for t in ("calibrated_sensor", "ego_pose", "sample", "sample_annotation",
                      "sample_data", "instance", "scene", "log"):
                tables[t] += rec[t]
            lidarseg += rec["lidarseg"]
            image_anns += rec["image_annotations"]
            channels.update(rec["channels"])
            for m in rec["map"]:
                maps.setdefault(m["token"], {**m, "log_tokens": []})["log_tokens"] += \
                    [lg["token"] for lg in rec["log"]]
        tables["map"] = list(maps.values())
        tables["sensor"] = [{"token": token("sensor", c), "channel": c, "modality": m}
                            for c, m in channels.items()]
        out = self.root / self.version
        out.mkdir(parents=True, exist_ok=True)
        for t in TABLES:
            S.atomic_write_text(out / f"{t}.json", json.dumps(tables[t], indent=1))
        if lidarseg:
            (self.root / "lidarseg" / self.version).mkdir(parents=True, exist_ok=True)
            S.atomic_write_text(out / "lidarseg.json", json.dumps(lidarseg, indent=1))
        S.atomic_write_text(out / "image_annotations.json", json.dumps(image_anns, indent=1))
        return {t: len(v) for t, v in tables.items()}
