"""Sessions: create (zip upload, synthetic, stream), list, status, cancel, delete, results."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from fastapi.responses import FileResponse, PlainTextResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from server.budget import MAX_FRAMES_OPTION, MAX_STRIDE
from server.decoding import DecodeFailed, shared_helper
from server.deps import get_manager, get_render_pools, get_settings, require_token
from server.errors import strip_paths, validation_message
from server.render_calls import LiveMesh, MapMesh, PlyMesh, export_mesh
from server.render_pools import HELPER_RESPONSES, RenderPools, http_answers
from server.rendering import NoMapYet
from server.schemas import ErrorOut, SessionCreated, SessionCreateJSON, SessionOut, SessionOutputs
from server.session_status import manager_stream_fields
from server.sessions import SessionManager, SessionNotFound, SessionStatus, check_session_id, new_session_id
from server.settings import Settings
from server.upload import (
    MAX_AGENTS,
    UploadError,
    ZipLimits,
    dataset_root,
    disk_full_error,
    extract_zip,
    inspect_dataset,
    parse_color_camera,
    parse_depth_scale,
    parse_intrinsics,
    is_disk_full,
    remove_tree,
    save_upload,
)
from server.worker import SourceSpec
from slam import FORMATS, DataError
from slam.data.images import ImageTooLarge

router = APIRouter(prefix="/api/sessions", tags=["sessions"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

MESH_MEDIA_TYPES = {"ply": "application/octet-stream", "glb": "model/gltf-binary", "obj": "text/plain"}
PRESETS = ("test", "cpu", "paper", "gpu")

_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["file"],
    "properties": {
        "file": {"type": "array", "items": {"type": "string", "format": "binary"}, "minItems": 1,
                 "maxItems": MAX_AGENTS,
                 "description": "zip of a TUM RGB-D, Replica, ScanNet or 7-Scenes folder; several 'file' parts "
                                "make one collaborative session, one agent per part in the order given (each "
                                "opened with the same options)"},
        "format": {"type": "string", "enum": list(FORMATS[:-1]), "default": "auto"},
        "preset": {"type": "string", "enum": list(PRESETS)},
        "intrinsics": {"type": "string", "description": "fx,fy,cx,cy (replaces the format's camera)",
                       "example": "517.3,516.5,318.6,255.3"},
        "depth_scale": {"type": "number", "description": "raw depth units per metre", "example": 5000},
        "color_intrinsics": {"type": "string",
                             "description": "colour from its own camera: fx,fy,cx,cy,width,height[,k1,k2,p1,p2[,k3]] "
                                            "of the colour images; colour is registered onto the depth camera",
                             "example": "1050,1050,959.5,539.5,1920,1080"},
        "depth_to_color": {"type": "string",
                           "description": "with color_intrinsics: the depth camera's frame in the colour camera's, "
                                          "16 numbers row-major (default identity)"},
        "stride": {"type": "integer", "minimum": 1, "maximum": MAX_STRIDE, "default": 1},
        "max_frames": {"type": "integer", "minimum": 1, "maximum": MAX_FRAMES_OPTION},
    },
}
_CREATE_OPENAPI = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
            "application/json": {
                "schema": SessionCreateJSON.model_json_schema(),
                "examples": {
                    "synthetic": {"value": {"source": "synthetic", "spec": "orbit?frames=60&width=160&height=120",
                                            "preset": "test"}},
                    "stream": {"value": {"source": "stream", "intrinsics": "525,525,319.5,239.5",
                                         "depth_scale": 5000}},
                },
            },
        },
    }
}


def session_out(manager: SessionManager, state: SessionStatus) -> SessionOut:
    directory = manager.session_dir(state.id)
    data = {k: v for k, v in state.to_json().items() if k not in ("spec", "specs")}
    data["agents"] = manager.agent_count(state.id)
    outputs = SessionOutputs(trajectory=(directory / "trajectory.txt").is_file() or state.frames_done > 0,
                             mesh=(directory / "mesh.ply").is_file() or bool(manager.live_meshes(state.id))
                             or (directory / "map.pt").is_file(),
                             map=(directory / "map.pt").is_file())
    files = [spec.name for spec in state.sources if spec.name]
    data.update(manager_stream_fields(manager, state))  # a stream's frames sent, received, dropped
    return SessionOut(**data, outputs=outputs, files=files, phase_elapsed_s=_phase_elapsed(state))


def _phase_elapsed(state: SessionStatus) -> float | None:
    """Seconds since the current phase began (server clock, so the page needs no clock of its own)."""
    if state.phase == "done" or not state.phase_started:
        return None
    try:
        started = datetime.fromisoformat(state.phase_started)
    except ValueError:
        return None
    return round(max(0.0, (datetime.now(timezone.utc) - started).total_seconds()), 1)


def _default_preset() -> str:
    from slam import default_preset_name

    return default_preset_name()


def _form_text(form, name: str) -> str | None:
    value = form.get(name)
    if value is None or isinstance(value, UploadFile):
        return None
    value = value.strip()
    return value or None


def _form_int(form, name: str, maximum: int) -> int | None:
    text = _form_text(form, name)
    if text is None:
        return None
    if len(text) > 20:
        raise UploadError(f"{name}: expected a whole number from 1 to {maximum}, got {text[:20]!r}...")
    try:
        value = int(text)
    except ValueError:
        raise UploadError(f"{name}: expected a whole number, got {text!r}") from None
    if not 1 <= value <= maximum:
        raise UploadError(f"{name}: must be between 1 and {maximum}, got {value}")
    return value


def _upload_spec(form) -> tuple[SourceSpec, str]:
    """Options of a zip upload from the multipart form (validated, no files touched yet)."""
    fmt = _form_text(form, "format") or "auto"
    if fmt not in FORMATS or fmt == "synthetic":
        raise UploadError(f"format: expected one of {', '.join(FORMATS[:-1])}, got {fmt!r}")
    preset = _form_text(form, "preset") or _default_preset()
    if preset not in PRESETS:
        raise UploadError(f"preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
    intrinsics = _form_text(form, "intrinsics")
    depth_scale = _form_text(form, "depth_scale")
    color_intrinsics, depth_to_color = parse_color_camera(_form_text(form, "color_intrinsics"),
                                                          _form_text(form, "depth_to_color"))
    spec = SourceSpec(kind="dataset", format=fmt,
                      intrinsics=None if intrinsics is None else parse_intrinsics(intrinsics),
                      depth_scale=None if depth_scale is None else parse_depth_scale(depth_scale),
                      color_intrinsics=color_intrinsics, depth_to_color=depth_to_color,
                      stride=_form_int(form, "stride", MAX_STRIDE) or 1,
                      max_frames=_form_int(form, "max_frames", MAX_FRAMES_OPTION))
    return spec, preset


def client_file_name(filename: str | None) -> str | None:
    """The last part of a client's file name, printable and at most 80 characters: a label."""
    name = (filename or "").replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(c for c in name if c.isprintable())[:80].strip()
    return name or None


def _part_label(index: int, count: int, upload: UploadFile) -> str:
    """How an error names a file part: ``file 2 of 3 ('b.zip')`` (the client's name, quoted, never a path)."""
    name = (upload.filename or "").replace("\n", " ")[:80]
    return f"file {index + 1} of {count}" + (f" ({name!r})" if name else "")


def _unpack_dataset(settings: Settings, session_dir: Path, upload: UploadFile, spec: SourceSpec,
                    input_dir: Path | None = None) -> SourceSpec:
    """Save, check and extract the zip into ``input_dir`` (default ``session_dir/input``), find
    the dataset folder, open its first frame. Runs in a worker thread; the caller removes the
    session folder on error."""
    from dataclasses import replace

    input_dir = input_dir or session_dir / "input"
    zip_path = settings.uploads_dir / f"{session_dir.name}.zip"
    try:
        save_upload(upload.file, zip_path, settings.max_upload_bytes)
        extract_zip(zip_path, input_dir, ZipLimits(settings.max_zip_entries, settings.max_unzipped_bytes))
        root = dataset_root(input_dir)
        try:
            # Out of this process: the images are untrusted (server.decoding).
            fmt = shared_helper().call(inspect_dataset, str(root), spec)
        except ImageTooLarge as error:
            raise UploadError(f"the dataset cannot be read: {error}", status=413) from None
        except DataError as error:
            raise UploadError(f"the dataset cannot be read: {error}") from None
        except DecodeFailed as error:
            raise UploadError(f"the dataset cannot be read: {error}", status=413) from None
        return replace(spec, path=str(root), format=fmt, name=client_file_name(upload.filename))
    except UploadError as error:
        # Messages name files: show them as the archive has them, never as server paths
        # (which would also show the id of a session that is not created after all).
        message = strip_paths(strip_paths(str(error), input_dir, "the top level of the zip"), zip_path, "the upload")
        raise UploadError(message, status=error.status) from None
    finally:
        zip_path.unlink(missing_ok=True)


def _unpack_datasets(settings: Settings, session_dir: Path, uploads: list[UploadFile],
                     spec: SourceSpec) -> list[SourceSpec]:
    """Every part of an upload, one agent each (``input/`` for one part, ``input/<k>/`` for
    several), all checked before the session exists. On any error the session folder is
    removed again; with several parts the error names the part."""
    specs = []
    try:
        for k, upload in enumerate(uploads):
            input_dir = session_dir / "input" if len(uploads) == 1 else session_dir / "input" / str(k)
            try:
                specs.append(_unpack_dataset(settings, session_dir, upload, spec, input_dir))
            except UploadError as error:
                if len(uploads) == 1:
                    raise
                raise UploadError(f"{_part_label(k, len(uploads), upload)}: {error}", status=error.status) from None
        return specs
    except BaseException:
        remove_tree(session_dir)
        raise


def _json_spec(body: SessionCreateJSON) -> tuple[list[SourceSpec], str]:
    """The sources of a JSON request: synthetic (one, or one per listed spec) or a stream."""
    preset = body.preset or _default_preset()
    if body.live and body.source != "stream":
        raise UploadError("live: only a stream comes from a camera at its own rate")
    if body.source == "synthetic":
        from slam.data.synthetic import parse_synthetic_spec

        texts = [body.spec] if isinstance(body.spec, str) else list(body.spec)
        specs = []
        for k, text in enumerate(texts):
            spec_text = text.removeprefix("synthetic:")
            try:
                parse_synthetic_spec(spec_text)
            except DataError as error:
                where = "spec" if isinstance(body.spec, str) else f"spec[{k}] (agent {k})"
                raise UploadError(f"{where}: {error}") from None
            specs.append(SourceSpec(kind="synthetic", path=spec_text, format="synthetic", max_frames=body.max_frames))
        return specs, preset
    if not isinstance(body.spec, str):
        raise UploadError("spec: a list of specs is for synthetic sessions; a stream's frames name their agent")
    intrinsics = None if body.intrinsics is None else parse_intrinsics(body.intrinsics)
    depth_scale = None if body.depth_scale is None else parse_depth_scale(body.depth_scale)
    color_intrinsics, depth_to_color = parse_color_camera(body.color_intrinsics, body.depth_to_color)
    return [SourceSpec(kind="stream", format="stream", intrinsics=intrinsics, depth_scale=depth_scale,
                       color_intrinsics=color_intrinsics, depth_to_color=depth_to_color, live=body.live)], preset


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SessionCreated,
             openapi_extra=_CREATE_OPENAPI,
             responses={400: {"model": ErrorOut}, 413: {"model": ErrorOut}, 415: {"model": ErrorOut},
                        422: {"model": ErrorOut}, 507: {"model": ErrorOut, "description": "the server's disk is full"},
                        429: {"model": ErrorOut, "description": "the queue of sessions waiting to start is full "
                                                                "(VOXFUSION_MAX_QUEUED); retry after Retry-After seconds",
                              "headers": {"Retry-After": {"schema": {"type": "integer"},
                                                          "description": "seconds to wait"}}}},
             summary="Create a session from a dataset zip, the synthetic source or a stream")
async def create_session(request: Request, manager: SessionManager = Depends(get_manager),
                         settings: Settings = Depends(get_settings)) -> SessionCreated:
    """Multipart with a ``file`` (zip of a dataset folder; ``format``, ``preset``, ``intrinsics``,
    ``depth_scale``, ``stride``, ``max_frames`` optional), or JSON ``{"source": "synthetic"}`` /
    ``{"source": "stream"}``. Several ``file`` parts are one collaborative session, one agent per
    part in the order given; a JSON ``spec`` list is one synthetic agent per spec. Every zip is
    validated and its first frame read before the session is queued; every problem is a 4xx
    that says what is wrong (and which part)."""
    manager.check_queue_room()  # 429 before a large upload is read, not after
    content_type = request.headers.get("content-type", "")
    session_id = new_session_id()
    if content_type.startswith("multipart/form-data"):
        try:
            form = await request.form(max_files=MAX_AGENTS, max_fields=20)
        except StarletteHTTPException as error:  # Starlette's "Too many files" and friends
            raise UploadError(f"the form cannot be read: {error.detail} (at most {MAX_AGENTS} 'file' parts)",
                              status=error.status_code) from None
        except OSError as error:  # the parts spool to temporary files, which a full disk refuses
            if is_disk_full(error):
                raise disk_full_error("the upload") from None
            raise
        parts = form.getlist("file")
        uploads = [part for part in parts if isinstance(part, UploadFile)]
        if not parts:
            raise UploadError("file: a zip of the dataset is required in the multipart field 'file'")
        if len(uploads) != len(parts):
            bad = next(k for k, part in enumerate(parts) if not isinstance(part, UploadFile))
            raise UploadError(f"file {bad + 1} of {len(parts)}: the 'file' field must be a file (a zip), not text")
        spec, preset = _upload_spec(form)
        specs = await run_in_threadpool(_unpack_datasets, settings, manager.session_dir(session_id), uploads, spec)
    elif content_type.startswith("application/json"):
        try:
            body = SessionCreateJSON.model_validate(json.loads(await request.body()))
        except json.JSONDecodeError as error:
            raise UploadError(f"the body is not valid JSON ({error})", status=400) from None
        except UnicodeDecodeError:
            raise UploadError("the body is not valid JSON: it is not UTF-8 text", status=400) from None
        except ValidationError as error:
            raise UploadError(validation_message(
                {**e, "loc": ("body", *e["loc"])} for e in error.errors())) from None
        specs, preset = _json_spec(body)
    else:
        raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
                            "send multipart/form-data with a zip in 'file', or application/json")
    created = manager.create(session_id, specs, preset)
    return SessionCreated(id=created.id, status=created.status)


@router.get("", response_model=list[SessionOut], summary="All sessions, newest first")
def list_sessions(manager: SessionManager = Depends(get_manager)) -> list[SessionOut]:
    listed = []
    for state in manager.list():
        try:
            listed.append(session_out(manager, state))
        except SessionNotFound:  # deleted while the list was being made: not listed
            continue
    return listed


@router.get("/{session_id}", response_model=SessionOut, summary="Status of one session")
def get_session(session_id: str, manager: SessionManager = Depends(get_manager)) -> SessionOut:
    return session_out(manager, manager.get(check_session_id(session_id)))


@router.post("/{session_id}/cancel", response_model=SessionOut, summary="Stop a session, keep its results")
def cancel_session(session_id: str, manager: SessionManager = Depends(get_manager)) -> SessionOut:
    return session_out(manager, manager.cancel(check_session_id(session_id)))


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT, summary="Cancel and delete a session")
def delete_session(session_id: str, manager: SessionManager = Depends(get_manager)) -> Response:
    manager.delete(check_session_id(session_id))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def trajectory_file(directory: Path, agent: int) -> Path:
    """Where the runtime writes ``agent``'s trajectory: ``trajectory.txt`` for agent 0 (and a
    single-agent run), ``trajectory_<k>.txt`` for every agent of a collaborative run."""
    return directory / ("trajectory.txt" if agent == 0 else f"trajectory_{agent}.txt")


@router.get("/{session_id}/trajectory", response_class=PlainTextResponse,
            responses={200: {"content": {"text/plain": {"example": "# timestamp tx ty tz qx qy qz qw\n"
                                                                   "0.000000 0.1 0.2 1.4 0 0 0 1\n"}}},
                       409: {"model": ErrorOut}},
            summary="Estimated trajectory (TUM text) of one agent, also while running")
def get_trajectory(session_id: str,
                   agent: int = Query(0, ge=0, le=MAX_AGENTS - 1,
                                      description="agent (camera) of a collaborative session; 0 is the first"),
                   manager: SessionManager = Depends(get_manager)) -> Response:
    """All agents' trajectories share one world frame (the first agent's first camera). While
    the session runs, poses tracked so far, moved with their maps by loop closures."""
    from slam import Trajectory, format_tum

    directory = manager.session_dir(check_session_id(session_id))
    state = manager.get(session_id)
    path = trajectory_file(directory, agent)
    agents = manager.agent_count(session_id)
    if path.is_file() and state.status in ("finished", "failed", "cancelled"):
        return PlainTextResponse(path.read_text())
    _, stamps, poses = manager.tracked_poses(session_id, agent)
    if len(stamps) == 0:
        if path.is_file():
            return PlainTextResponse(path.read_text())
        if agent >= agents and agent not in manager.tracked_agents(session_id):
            which = "one agent (0)" if agents == 1 else f"{agents} agents (0 to {agents - 1})"
            running = "" if state.status in ("finished", "failed", "cancelled") else " so far"
            raise HTTPException(status.HTTP_404_NOT_FOUND,
                                f"session {session_id} has no agent {agent}: it has {which}{running}")
        raise HTTPException(status.HTTP_409_CONFLICT, f"session {session_id} has no tracked poses yet"
                            + ("" if agent == 0 else f" for agent {agent}"))
    return PlainTextResponse(format_tum(Trajectory(stamps, poses)))


def parse_crop(text: str | None) -> tuple[list[float], list[float]] | None:
    """``xmin,ymin,zmin,xmax,ymax,zmax`` -> (min, max); 422 saying what is wrong."""
    if text is None or not text.strip():
        return None
    try:
        values = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not all(np.isfinite(values)):
        raise HTTPException(422, f"crop: expected six numbers xmin,ymin,zmin,xmax,ymax,zmax, got {text!r}")
    if not all(lo < hi for lo, hi in zip(values[:3], values[3:])):
        raise HTTPException(422, f"crop: every min must be below its max, got {text!r}")
    return values[:3], values[3:]


@router.get("/{session_id}/mesh", responses={200: {"content": {t: {} for t in set(MESH_MEDIA_TYPES.values())}},
                                             409: {"model": ErrorOut}, **HELPER_RESPONSES},
            summary="The current mesh (world frame, vertex colours), also while running")
async def get_mesh(session_id: str, format: Literal["ply", "glb", "obj"] = Query("ply"),
                   crop: str | None = Query(None, examples=["-1,-1,0,1,1,2"],
                                            description="xmin,ymin,zmin,xmax,ymax,zmax (world frame, metres): only "
                                                        "the faces inside this box"),
                   manager: SessionManager = Depends(get_manager),
                   pools: RenderPools = Depends(get_render_pools)) -> Response:
    """Finished sessions serve ``mesh.ply`` (converted for GLB/OBJ). Running sessions serve the
    latest live meshes of their maps, or extract one from the latest ``map.pt``. Conversion,
    extraction and cropping run in a render helper (``server.render_calls.export_mesh``)."""
    box = parse_crop(crop)
    directory = manager.session_dir(check_session_id(session_id))
    state = manager.get(session_id)
    ply = directory / "mesh.ply"
    suffix = "_mesh" if box is None else "_mesh_crop"
    headers = {"Content-Disposition": f'attachment; filename="{session_id}{suffix}.{format}"'}
    source = mesh_source(manager, state, directory)
    if isinstance(source, PlyMesh) and format == "ply" and box is None:
        return FileResponse(ply, media_type=MESH_MEDIA_TYPES["ply"], filename=f"{session_id}_mesh.ply")
    try:
        with http_answers(f"mesh of session {session_id}"):
            data = await pools.render.run(export_mesh, source, format, box)
    except NoMapYet as error:
        if not isinstance(source, MapMesh) or not ply.is_file():
            raise HTTPException(status.HTTP_409_CONFLICT, f"session {session_id}: {error}") from None
        with http_answers(f"mesh of session {session_id}"):  # a map without a surface yet: the written mesh
            data = await pools.render.run(export_mesh, PlyMesh(str(ply)), format, box)
    return Response(data, media_type=MESH_MEDIA_TYPES[format], headers=headers)


def mesh_source(manager: SessionManager, state: SessionStatus, directory: Path) -> PlyMesh | LiveMesh | MapMesh:
    """Where a session's mesh comes from now: the written ``mesh.ply`` once it ended, else
    the live meshes, else its ``map.pt``, else a ``mesh.ply`` (409 without any)."""
    ply, map_path = directory / "mesh.ply", directory / "map.pt"
    if state.status in ("finished", "failed", "cancelled") and ply.is_file():
        return PlyMesh(str(ply))
    live = manager.live_meshes(state.id)
    if live:
        return LiveMesh([live[m] for m in sorted(live)])
    if map_path.is_file():
        return MapMesh(str(map_path), manager.render_threads())
    if ply.is_file():
        return PlyMesh(str(ply))
    raise HTTPException(status.HTTP_409_CONFLICT, f"session {state.id}: the session has no map yet: map.pt is "
                                                  "written after the first keyframes")
