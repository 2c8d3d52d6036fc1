"""The stereo rig of each vehicle in a set of logs, resolved once.

Each camera's model comes from the first CameraInfo on its topic when there is one, else from
the rig config (`logs.vehicles.<name>.rig.left/right`, which `--calib` fills from a Kalibr
file; distortion names like Kalibr's `radtan` mapped to ROS's). Its extrinsics (T_body_cam)
come from `/tf_static` (of the vehicle's own log when it is bound to one, else of the logs no
vehicle is bound to) when that links the vehicle's body frame to the camera's frame, else
from the rig config; a rectified pair with no extrinsics at all gets its right camera from the
rectified right projection matrix (the baseline along the left camera's x). `Calibration` resolves a
vehicle's rig once and keeps the outcome (the rig, or the error saying why there is none), so
streaming never goes back to the logs for it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from cvslam_cli.config import CameraConfig, LogsConfig
from cvslam_cli.errors import CalibrationError, CvslamError
from cvslam_cli.geometry.camera import CameraModel, StereoRig, translation_T
from cvslam_cli.geometry.rotations import invert_T, make_T, quat_xyzw_to_matrix
from cvslam_cli.io.mcap_source import LogSource, RawMessage
from cvslam_cli.io.topic_map import LogTopics

log = logging.getLogger("cvslam.calibration")

#: other names of the distortion models (Kalibr's radtan is ROS's plumb_bob)
DISTORTION_ALIASES = {
    "radtan": "plumb_bob",
    "radial-tangential": "plumb_bob",
    "fisheye": "equidistant",
}


def distortion_model_name(name: str) -> str:
    """The ROS name of a distortion model given under another name ('' -> 'none')."""
    return DISTORTION_ALIASES.get(name, name) or "none"


def camera_from_info(msg: Any, source: str) -> CameraModel:
    """CameraModel from a decoded sensor_msgs/msg/CameraInfo."""
    P = np.asarray(msg.p, dtype=float).reshape(3, 4)
    return CameraModel(
        width=int(msg.width),
        height=int(msg.height),
        K=np.asarray(msg.k, dtype=float).reshape(3, 3),
        D=np.asarray(msg.d, dtype=float),
        distortion_model=distortion_model_name(str(msg.distortion_model)),
        R_rect=np.asarray(msg.r, dtype=float).reshape(3, 3),
        P=P if np.any(P) else None,
        frame_id=str(msg.header.frame_id),
        source=source,
    )


def camera_from_config(cfg: CameraConfig, frame_id: str, source: str) -> CameraModel:
    """CameraModel from a configured camera (`logs.vehicles.<name>.rig.<side>`)."""
    K = np.array([[cfg.fx, 0.0, cfg.cx], [0.0, cfg.fy, cfg.cy], [0.0, 0.0, 1.0]])
    return CameraModel(
        width=cfg.width,
        height=cfg.height,
        K=K,
        D=np.asarray(cfg.distortion),
        distortion_model=distortion_model_name(cfg.distortion_model),
        T_body_cam=np.asarray(cfg.T_body_cam, dtype=float).reshape(4, 4),
        frame_id=frame_id,
        source=source,
    )


class StaticTransforms:
    """The tree of /tf_static transforms; `lookup(a, b)` gives T_a_b when a path exists."""

    def __init__(self) -> None:
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        self._edges.setdefault(parent, {})[child] = T_parent_child
        self._edges.setdefault(child, {})[parent] = invert_T(T_parent_child)

    def add_message(self, msg: Any) -> None:
        for tr in msg.transforms:
            t, q = tr.transform.translation, tr.transform.rotation
            T = make_T(
                quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([t.x, t.y, t.z])
            )
            self.add(_strip(tr.header.frame_id), _strip(tr.child_frame_id), T)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4)
        seen = {target}
        queue: deque[tuple[str, np.ndarray]] = deque([(target, np.eye(4))])
        while queue:
            frame, T_target_frame = queue.popleft()
            for nxt, T_frame_nxt in self._edges.get(frame, {}).items():
                if nxt in seen:
                    continue
                T = T_target_frame @ T_frame_nxt
                if nxt == source:
                    return T
                seen.add(nxt)
                queue.append((nxt, T))
        return None


def _strip(frame: str) -> str:
    return frame.lstrip("/")


class Calibration:
    """The stereo rigs of the vehicles of a set of logs (module docstring).

    `rig(vehicle)` resolves a vehicle's rig at its first call and returns the same rig, or
    raises the same error, ever after; `resolve(vehicles)` gives the outcomes without raising,
    for a stream to consult.
    """

    def __init__(
        self, sources: Sequence[LogSource], topics: LogTopics, cfg: LogsConfig, names: str
    ) -> None:
        self._sources = sources
        self._topics = topics
        self._cfg = cfg
        self._names = names
        self._tf: dict[tuple[int, ...], StaticTransforms] = {}
        self._outcomes: dict[str, StereoRig | CvslamError] = {}

    @property
    def static_transforms(self) -> StaticTransforms:
        """Every transform on `/tf_static` of the logs no vehicle is bound to."""
        bound = {i for v in self._topics.vehicles.values() if v.config.log for i in v.sources}
        return self._transforms(tuple(i for i in range(len(self._sources)) if i not in bound))

    def _transforms(self, logs: tuple[int, ...]) -> StaticTransforms:
        """The `/tf_static` transforms of the logs with these indices (read at first use)."""
        if logs not in self._tf:
            tf = self._tf[logs] = StaticTransforms()
            topic = self._cfg.tf_static_topic
            for i in self._topics.logs_of.get(topic, []):
                if i not in logs:
                    continue
                for raw in self._sources[i].messages([topic]):
                    if raw.schema_name == "tf2_msgs/msg/TFMessage":
                        tf.add_message(raw.msg)
        return self._tf[logs]

    def _vehicle_transforms(self, vehicle: str) -> StaticTransforms:
        """A bound vehicle's own log's transforms; the others', those of the unbound logs."""
        v = self._topics.vehicles[vehicle]
        return self._transforms(v.sources) if v.config.log else self.static_transforms

    def rig(self, vehicle: str) -> StereoRig:
        """Stereo calibration of `vehicle` (CalibrationError when none can be had)."""
        outcome = self._outcome(vehicle)
        if isinstance(outcome, CvslamError):
            raise outcome.with_traceback(None)
        return outcome

    def resolve(self, vehicles: Iterable[str]) -> dict[str, StereoRig | CvslamError]:
        """Each vehicle's rig, or the error saying why it has none."""
        return {v: self._outcome(v) for v in vehicles}

    def _outcome(self, vehicle: str) -> StereoRig | CvslamError:
        if vehicle not in self._outcomes:
            try:
                self._outcomes[vehicle] = self._resolve(vehicle)
            except CvslamError as exc:
                self._outcomes[vehicle] = exc
        return self._outcomes[vehicle]

    def _first(self, vehicle: str, topic: str) -> RawMessage | None:
        """The first message on a topic of `vehicle`'s logs."""
        for i in self._topics.vehicles[vehicle].sources:
            if topic in self._sources[i].topics():
                for raw in self._sources[i].messages([topic]):
                    return raw
        return None

    def _camera(self, vehicle: str, side: str) -> tuple[CameraModel, np.ndarray]:
        """One camera's model from CameraInfo or the rig config, and its configured
        extrinsics T_body_cam."""
        v = self._topics.vehicles[vehicle]
        cam_cfg = getattr(v.config.rig, side)
        info_topic = v.topic(f"{side}_info")
        raw = self._first(vehicle, info_topic) if f"{side}_info" in v.present else None
        if raw is not None:
            return camera_from_info(raw.msg, f"CameraInfo {info_topic}"), cam_cfg.T_body_cam
        if cam_cfg.configured:
            img = self._first(vehicle, v.topic(f"{side}_image"))
            frame_id = img.msg.header.frame_id if img else ""
            source = f"config logs.vehicles.{vehicle}.rig.{side}"
            return camera_from_config(cam_cfg, frame_id, source), cam_cfg.T_body_cam
        raise CalibrationError(
            f"{self._names}: vehicle {vehicle}: no calibration for the {side} camera "
            f"(no CameraInfo on {info_topic} and rig.{side} is not configured)"
        )

    def _resolve(self, vehicle: str) -> StereoRig:
        v = self._topics.vehicles[vehicle]
        body_frame = v.config.rig.body_frame.replace("{vehicle}", v.template_name or vehicle)
        tf = self._vehicle_transforms(vehicle)
        cams: list[CameraModel] = []
        for side in ("left", "right"):
            cam, extr = self._camera(vehicle, side)
            T_body_cam = tf.lookup(body_frame, cam.frame_id) if cam.frame_id else None
            if T_body_cam is None:
                T_body_cam = np.asarray(extr, dtype=float).reshape(4, 4)
            else:
                cam = dataclasses.replace(
                    cam, source=cam.source + f" + {self._cfg.tf_static_topic}"
                )
            cams.append(dataclasses.replace(cam, T_body_cam=T_body_cam))
        left, right = cams
        rig = StereoRig(left, right)
        b_p = rig.baseline_from_projection_m
        if rig.baseline_m < 1e-6 and b_p is not None and b_p > 0:
            # rectified pair with no extrinsics: the right camera sits b along the left's x
            right = dataclasses.replace(right, T_body_cam=left.T_body_cam @ translation_T(b_p))
            rig = StereoRig(left, right)
            log.debug(
                "%s: no stereo extrinsics given: right camera %.4f m along the left's x "
                "(from the right projection matrix, P[0,3] = -fx * baseline)",
                vehicle,
                b_p,
            )
        where = f"{self._names}: vehicle {vehicle}"
        left.validate(f"{where} left camera")
        right.validate(f"{where} right camera")
        if rig.baseline_m < 1e-6:
            raise CalibrationError(
                f"{self._names}: vehicle {vehicle}: no stereo extrinsics (zero baseline): "
                f"{self._cfg.tf_static_topic} does not link {body_frame} to the cameras' frames "
                f"({left.frame_id or 'no frame_id'}, {right.frame_id or 'no frame_id'}) and "
                f"logs.vehicles.{vehicle}.rig.left.T_body_cam and rig.right.T_body_cam put "
                "both cameras at the same place (identity when not set); give either "
                "(--calib camchain.yaml reads them from a Kalibr calibration)"
            )
        rig.validate(where)
        log.debug(
            "%s: calibration: left from %s, right from %s; %s, baseline %.4f m, %d x %d px, "
            "fx %.1f px, distortion %s",
            vehicle,
            left.source,
            right.source,
            "rectified" if rig.rectified else "unrectified",
            rig.baseline_m,
            left.width,
            left.height,
            left.fx,
            left.distortion_model,
        )
        return rig
