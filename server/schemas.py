"""Pydantic models of the HTTP API (only here, at the edge), with examples for the OpenAPI schema."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from server.budget import DEPTH_SCALE_RANGE, MAX_FRAMES_OPTION

EXAMPLE_POSE = [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, 1.0, -1.5], [0.0, -1.0, 0.0, 1.4], [0.0, 0.0, 0.0, 1.0]]
MAX_SIDE = 2048

Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)]
"""A 4x4 matrix as four rows of four numbers (the schema says so: a client that follows it
never meets the shape check)."""


class Strict(BaseModel):
    """A request body: unknown keys and non-finite numbers (NaN, Infinity) are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


MAX_EDGE_ANGLE_DEG = 85.0
"""How far from the optical axis an image edge may be (a pinhole camera's view is in front)."""
MIN_VIEW_ANGLE_DEG = 0.001
"""Narrowest field of view across the image (a longer focal length renders parallel rays)."""


def _view_error(axis: str, f: float, c: float, size: int) -> str | None:
    """Why focal length ``f`` and principal point ``c`` (pixels) cannot image ``size`` pixels
    along ``axis``, or None. Checked here, at the edge: a focal length such as 1e-300 passed
    ``> 0`` and then broke the ray traversal (a 500)."""
    edges = np.degrees(np.arctan2(np.array([-0.5, size - 0.5]) - c, f))
    if np.abs(edges).max() > MAX_EDGE_ANGLE_DEG:
        return (f"f{axis}={f:g} and c{axis}={c:g} put an edge of the {size}-pixel image {np.abs(edges).max():.1f} "
                f"degrees from the optical axis (at most {MAX_EDGE_ANGLE_DEG:g} for a pinhole camera): the focal "
                f"length is too short or the principal point too far outside the image")
    if edges[1] - edges[0] < MIN_VIEW_ANGLE_DEG:
        return (f"f{axis}={f:g} gives a field of view under {MIN_VIEW_ANGLE_DEG:g} degrees across {size} pixels: "
                f"the focal length is too long")
    return None


class Intrinsics(Strict):
    """A pinhole camera: focal lengths and principal point in pixels, image size. The image
    must lie within MAX_EDGE_ANGLE_DEG of the optical axis on both axes."""

    fx: float = Field(gt=0, examples=[200.0])
    fy: float = Field(gt=0, examples=[200.0])
    cx: float = Field(examples=[160.0])
    cy: float = Field(examples=[120.0])
    width: int = Field(ge=1, le=MAX_SIDE, examples=[320])
    height: int = Field(ge=1, le=MAX_SIDE, examples=[240])

    @model_validator(mode="after")
    def _sane_view(self) -> "Intrinsics":
        problems = [p for p in (_view_error("x", self.fx, self.cx, self.width),
                                _view_error("y", self.fy, self.cy, self.height)) if p]
        if problems:
            raise ValueError("; ".join(problems))
        return self


def _check_matrix(value: object) -> object:
    """Before the type check, so that a wrong shape reads as one sentence (not one error per row)."""
    if isinstance(value, list) and (len(value) != 4 or any(isinstance(row, list) and len(row) != 4 for row in value)):
        raise ValueError("must be a 4x4 nested list")
    return value


def _check_matrices(value: object) -> object:
    return [_check_matrix(m) for m in value] if isinstance(value, list) else value


class CropBox(Strict):
    """An axis-aligned box in the world frame (metres): only what lies inside it is rendered."""

    min: tuple[float, float, float] = Field(examples=[[-1.0, -1.0, 0.0]])
    max: tuple[float, float, float] = Field(examples=[[1.0, 1.0, 2.0]])

    @model_validator(mode="after")
    def _ordered(self) -> "CropBox":
        if not all(lo < hi for lo, hi in zip(self.min, self.max)):
            raise ValueError("every min must be below its max")
        return self


class CameraRequest(Strict):
    """A camera to render: ``T_world_cam`` is camera-to-world (OpenCV axes: x right, y down, z forward)."""

    T_world_cam: Matrix4 = Field(examples=[EXAMPLE_POSE])
    intrinsics: Intrinsics
    crop: CropBox | None = Field(None, description="render only what lies inside this box (the render call)")

    _matrix = field_validator("T_world_cam", mode="before")(_check_matrix)

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "T_world_cam": EXAMPLE_POSE,
        "intrinsics": {"fx": 200.0, "fy": 200.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240}}]})


class SessionCreateJSON(Strict):
    """A session without an upload: the synthetic generator, or frames streamed later."""

    source: Literal["synthetic", "stream"] = Field(examples=["synthetic"])
    spec: str | list[str] = Field(
        "orbit?frames=120&width=320&height=240",
        description="synthetic scene spec (kind?frames=&width=&height=&seed=&noise=&agent=&agents=), or a "
                    "list of specs for a collaborative session: one agent each, in order "
                    "(e.g. ['agents?agent=0&agents=2', 'agents?agent=1&agents=2'])",
        examples=["orbit?frames=60&width=160&height=120"])
    preset: Literal["test", "cpu", "paper", "gpu"] | None = Field(None, description="config preset; default cpu without a GPU, gpu with one")
    intrinsics: str | None = Field(None, description="stream: 'fx,fy,cx,cy' (else on the first frame)",
                                   examples=["525,525,319.5,239.5"])
    depth_scale: float | None = Field(None, ge=DEPTH_SCALE_RANGE[0], le=DEPTH_SCALE_RANGE[1],
                                      description="stream: raw depth units per metre (default 1000)")
    color_intrinsics: str | None = Field(None, max_length=400,
                                         description="stream: colour from its own camera, "
                                                     "'fx,fy,cx,cy,width,height[,k1,k2,p1,p2[,k3]]' of the colour "
                                                     "images, which are then registered onto the depth camera",
                                         examples=["615,615,320,240,640,480"])
    depth_to_color: str | None = Field(None, max_length=400,
                                       description="stream, with color_intrinsics: the depth camera's frame in the "
                                                   "colour camera's, 16 numbers row-major (default identity)")
    max_frames: int | None = Field(None, ge=1, le=MAX_FRAMES_OPTION)
    live: bool = Field(False, description="stream: frames come from a camera at its own rate, which does not "
                                          "wait: the tracker never waits for the mapper, which maps the newest "
                                          "frames it has time for (runtime.live)")

    @field_validator("spec")
    @classmethod
    def _spec_lengths(cls, value: str | list[str]) -> str | list[str]:
        from server.upload import MAX_AGENTS

        if isinstance(value, list) and not 1 <= len(value) <= MAX_AGENTS:
            raise ValueError(f"a list of specs has one per agent: 1 to {MAX_AGENTS}, got {len(value)}")
        for text in [value] if isinstance(value, str) else value:
            if len(text) > 200:
                raise ValueError(f"a synthetic spec has at most 200 characters, got {len(text)}")
        return value

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"source": "synthetic", "spec": "orbit?frames=60&width=160&height=120", "preset": "test"},
        {"source": "synthetic", "spec": ["agents?agent=0&agents=2&frames=60", "agents?agent=1&agents=2&frames=60"],
         "preset": "test"},
        {"source": "stream", "intrinsics": "525,525,319.5,239.5", "depth_scale": 5000, "preset": "cpu"}]})


class SessionCreated(BaseModel):
    id: str = Field(examples=["3f2a9c0d1b7e"])
    status: str = Field(examples=["queued"])


class SessionOutputs(BaseModel):
    """Which result files exist now."""

    trajectory: bool
    mesh: bool
    map: bool


class WorkerOut(BaseModel):
    """Where a session runs or ran."""

    executor: Literal["local", "ray"] = Field(examples=["ray"], description="VOXFUSION_EXECUTOR when it started")
    node: str | None = Field(examples=["9dc585f1d37e0c6a9312d164050fb426513c65e6f2f52c30da2c29f5"],
                             description="local: this server's host name; ray: the id of the cluster node")
    address: str | None = Field(None, examples=["10.0.0.12"], description="ray: the node's IP address")


class SessionOut(BaseModel):
    id: str = Field(examples=["3f2a9c0d1b7e"])
    status: Literal["queued", "running", "finished", "failed", "cancelled"]
    frames_done: int = Field(examples=[42])
    latest_frame: int | None = Field(None, examples=[41], description="the first agent's newest tracked frame, "
                                                                       "its index in the input (a stream: in the "
                                                                       "order sent); null before the first")
    frames_total: int | None = Field(examples=[120], description="None for streams")
    fps: float = Field(examples=[3.5], description="frames tracked (all agents) per second of the tracking phase; "
                                                  "fixed once tracking ends (run.json's fps counts the whole run)")
    keyframes: int
    frames_skipped: int = Field(0, examples=[0], description="input frames left out because they could not be read "
                                                           "(an upload's corrupt frames, a stream's refused ones); "
                                                           "counted once the session has ended")
    color_camera: str | None = Field(None, examples=["estimated from the data (scale 1.000, shift +0.0, +0.0 px, "
                                                      "confidence 0.00): not applied, registered already: identity "
                                                      "is the best warp within a pixel"],
                                     description="how the colour came onto the depth camera: given (a calibration) "
                                                 "or estimated from the data, and whether it was applied; known "
                                                 "once the session has ended")
    maps: int = Field(examples=[2], description="maps (submaps) of all agents")
    loops: int = Field(examples=[1], description="accepted loop closures")
    agents: int = Field(1, examples=[1], description="agents (cameras): an upload's file parts, or the agents "
                                                      "a stream has seen")
    phase: Literal["queued", "starting", "tracking", "refining", "writing", "done"] = Field(
        examples=["tracking"],
        description="what a session does now: queued; starting (its worker loads, the mapper starts: seconds; "
                    "a stream's frames sent now wait); tracking (frames are read and tracked, maps grow); refining "
                    "(the input ended: final global bundle adjustment and mesh, minutes on a long run); writing "
                    "(trajectories and run.json); done (ended, however: see status)")
    phase_started: str | None = Field(None, examples=["2025-01-01T12:03:10+00:00"],
                                      description="when the current phase began (ISO 8601, UTC)")
    phase_elapsed_s: float | None = Field(None, examples=[42.0],
                                          description="seconds in the current phase so far (server clock); "
                                                      "null once done")
    phase_budget_s: float | None = Field(None, examples=[None], deprecated=True,
                                         description="no longer set: see phase_step and phase_estimate_s")
    phase_step: str | None = Field(
        None, examples=["colour_fit"],
        description="while refining or writing: the end-of-run step that runs: bundle_adjustment, retracking, "
                    "colour_fit, mesh (refining), outputs (writing) (the final bundle adjustment, the "
                    "re-tracking of the frames against the final maps, the fine colour fit, the map and mesh, the "
                    "trajectories and run.json); phase_started and phase_elapsed_s then count from the step's "
                    "start; null outside them")
    phase_estimate_s: float | None = Field(None, examples=[40.0],
                                           description="about how many seconds phase_step should take (a time cap "
                                                       "or a forecast from the run so far); a step may run past "
                                                       "it; null when nothing predicts it")
    frames_sent: int | None = Field(None, examples=[300],
                                    description="a stream's frames sent by its clients: received + dropped + "
                                                "refused; null for other sources")
    frames_received: int | None = Field(None, examples=[290],
                                        description="a stream's frames accepted by the server; null for other "
                                                    "sources")
    frames_dropped: int | None = Field(None, examples=[10],
                                       description="a stream's frames dropped because the session's buffer was "
                                                   "full (503); null for other sources")
    ate_rmse_m: float | None = Field(
        examples=[0.012], description="absolute trajectory error (RMSE, metres, after rigid alignment) of the first "
                                      "agent against the input's ground truth: so far while tracking, final once "
                                      "finished; null without ground truth")
    error: str | None = Field(examples=[None], description="why the session failed; an interrupted session (the "
                                                           "server stopped or was killed) says 'interrupted: ...'")
    created: str = Field(examples=["2025-01-01T12:00:00+00:00"])
    source: str = Field(examples=["synthetic:orbit?frames=120&width=320&height=240"])
    files: list[str] = Field([], examples=[["rgbd_dataset_freiburg1_desk.zip"]],
                             description="an upload's file names as the client gave them, one per agent (labels only)")
    preset: str = Field(examples=["cpu"])
    worker: WorkerOut | None = Field(None, description="where the session runs or ran; null while queued (and for "
                                                       "sessions from before this was recorded)")
    outputs: SessionOutputs


class SeriesOut(BaseModel):
    """What the page plots: positions in metres, times in seconds."""

    agent: int = Field(examples=[0])
    timestamps: list[float] = Field(examples=[[0.0, 0.033]], description="the estimated frames' input timestamps")
    estimated: list[list[float]] = Field(examples=[[[0.0, 0.0, 1.4], [0.01, 0.0, 1.4]]],
                                         description="camera centres per estimated frame: in the ground truth's "
                                                     "frame when aligned, else in the session's world frame")
    aligned: bool = Field(description="the estimate was aligned onto the ground truth (3 or more pairs)")
    ground_truth: list[list[float]] | None = Field(examples=[[[0.0, 0.0, 1.4]]],
                                                   description="the input's ground-truth camera centres (all "
                                                               "frames); null without ground truth")
    ground_truth_note: str | None = Field(None, examples=["the ground truth is not shown: traj.txt has more than "
                                                          "200000 lines"],
                                          description="why the input's ground truth is not shown (too large to "
                                                      "read, or being read); null otherwise")
    error_m: list[float | None] | None = Field(examples=[[0.002, 0.003]],
                                               description="per estimated frame, its distance to its ground-truth "
                                                           "pose after alignment (null: no pair); null when not "
                                                           "aligned")
    ate_rmse_m: float | None = Field(examples=[0.0025], description="RMSE of error_m")
    fps_time_s: list[float] = Field(examples=[[0.5, 1.0]], description="seconds since tracking began")
    fps_frames: list[int] = Field(examples=[[2, 5]], description="frames tracked by then (all agents)")


class FrameAccepted(BaseModel):
    index: int = Field(examples=[0], description="the frame's index among its agent's frames (from 0)")
    frames_received: int = Field(examples=[1], description="frames of all agents together")
    agent: int = Field(0, examples=[0])


class StreamFinished(BaseModel):
    frames: int = Field(examples=[240])


class ARObject(Strict):
    """A virtual object: exactly one of ``shape`` or ``asset``; placed by ``T_world_obj`` and ``scale``."""

    shape: Literal["cube", "sphere", "cylinder", "axes"] | None = None
    asset: str | None = Field(None, description="id from POST /api/assets")
    T_world_obj: Matrix4 | None = Field(
        None, description="object-to-world pose; left out, the object is placed in front of the camera: on its "
                          "optical axis, before the surface at the image centre (1 m ahead without depth there), "
                          "its axes the world's")
    scale: float = Field(1.0, gt=0, le=100)
    color: list[float] | None = Field(None, min_length=3, max_length=3, description="[r, g, b] in [0, 1]")

    _matrix = field_validator("T_world_obj", mode="before")(_check_matrix)


class ARRequest(Strict):
    """Virtual objects composited into a rendered view or an input frame, with occlusion."""

    background: str = Field("render", pattern=r"^(render|frame:\d{1,7})$",
                            description="'render' (neural render of the map) or 'frame:N' (the N-th input frame)")
    agent: int = Field(0, ge=0, le=63, description="whose input frame 'frame:N' is in a collaborative session "
                                                   "(the k-th source, or a stream's agent k); 0 by default")
    T_world_cam: Matrix4 | None = Field(None, description="required for 'render'; default for 'frame:N': its estimated pose")
    intrinsics: Intrinsics | None = Field(None, description="required for 'render'; default for 'frame:N': the frame's")
    objects: list[ARObject] = Field(max_length=64)

    _matrix = field_validator("T_world_cam", mode="before")(_check_matrix)

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "background": "render",
        "T_world_cam": EXAMPLE_POSE,
        "intrinsics": {"fx": 200.0, "fy": 200.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240},
        "objects": [{"shape": "cube", "T_world_obj": [[1, 0, 0, 0.5], [0, 1, 0, 0.5], [0, 0, 1, 0.3], [0, 0, 0, 1]],
                     "scale": 0.3, "color": [0.9, 0.2, 0.2]}]}]})


class PickRequest(CameraRequest):
    """A pixel of a camera's image (as in the render call) to back-project onto the map."""

    u: float = Field(ge=0, examples=[160.0], description="column, pixels")
    v: float = Field(ge=0, examples=[120.0], description="row, pixels")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "T_world_cam": EXAMPLE_POSE, "u": 160, "v": 120,
        "intrinsics": {"fx": 200.0, "fy": 200.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240}}]})


class PickOut(BaseModel):
    hit: bool
    point: list[float] | None = Field(None, examples=[[0.4, 1.2, 0.75]])
    normal: list[float] | None = Field(None, examples=[[0.0, 0.0, 1.0]])
    depth: float | None = Field(None, examples=[1.9])


class AssetOut(BaseModel):
    id: str = Field(examples=["9c1d2e3f4a5b6c7d"])
    vertices: int
    faces: int


class ViewerCameraOut(BaseModel):
    """The viewpoint of the browser that moved last, ready for the render call."""

    T_world_cam: Matrix4
    intrinsics: Intrinsics


class SessionCameraOut(BaseModel):
    """A session's newest tracked camera: where the render panel starts."""

    agent: int = Field(examples=[0])
    index: int | None = Field(examples=[41], description="the frame's index among its agent's frames (null: "
                                                          "read back from the written trajectory)")
    timestamp: float = Field(examples=[1.366])
    T_world_cam: Matrix4
    intrinsics: Intrinsics = Field(description="the input camera, at the resolution it was tracked")


class PathRequest(Strict):
    """A fly-through video: keyframe poses (camera-to-world, OpenCV axes), the camera every frame
    is rendered with, and how to play the path (see ``slam.camera_path``)."""

    keyframes: list[Matrix4] = Field(min_length=2, max_length=64, examples=[[EXAMPLE_POSE, EXAMPLE_POSE]],
                                     description="2 to 64 poses T_world_cam the path passes through, in order")
    intrinsics: Intrinsics
    duration_s: float = Field(6.0, gt=0, le=150, examples=[6.0])
    fps: float = Field(24.0, ge=1, le=60, examples=[24.0])
    loop: bool = Field(False, description="return to the first keyframe (a closed path)")
    outputs: list[Literal["color", "depth", "normals"]] = Field(
        ["color", "depth", "normals"], min_length=1, max_length=3,
        description="panels side by side, in this order: rendered colour, depth (turbo colour map), normals")
    depth_range: tuple[float, float] | None = Field(None, examples=[[0.3, 4.0]],
                                                    description="metres shown from blue to red (default: the first "
                                                                "frame's 2nd-98th percentile)")
    crop: "CropBox | None" = Field(None, description="render only what lies inside this box")

    _matrices = field_validator("keyframes", mode="before")(_check_matrices)

    @model_validator(mode="after")
    def _sane(self) -> "PathRequest":
        if self.intrinsics.width * self.intrinsics.height > 640 * 480:
            raise ValueError("a video frame may have at most 640x480 pixels per panel")
        if self.depth_range is not None and not 0 <= self.depth_range[0] < self.depth_range[1]:
            raise ValueError("depth_range: near must be at least 0 and below far")
        return self


class PathPreview(Strict):
    """A camera path to draw in the 3D viewer (its shape only: no camera, no timing)."""

    keyframes: list[Matrix4] = Field(min_length=2, max_length=64, examples=[[EXAMPLE_POSE, EXAMPLE_POSE]])
    loop: bool = False

    _matrices = field_validator("keyframes", mode="before")(_check_matrices)


class PathJobOut(BaseModel):
    id: str = Field(examples=["a1b2c3d4e5f6"])
    state: Literal["queued", "rendering", "finished", "failed"]
    frames_done: int = Field(examples=[48])
    frames_total: int = Field(examples=[144])
    error: str | None = Field(None, examples=[None])
    video: str = Field(examples=["/api/sessions/3f2a9c0d1b7e/render/path/a1b2c3d4e5f6/video"],
                       description="where the MP4 is served once finished")


class ViewerInfo(BaseModel):
    enabled: bool
    port: int | None = Field(description="viser's own port (its client files; its WebSocket admits only the "
                                          "token-checked relay at /viewer)")
    clients: int
    selected: str | None = Field(None, description="the session the viewer shows (the page selects the one it shows)")


class ErrorOut(BaseModel):
    detail: str = Field(examples=["depth: depth must be a 16-bit PNG, got 8-bit"])
