// What the page says about a session's status (GET /api/sessions): its phase, the end-of-run
// step with its time against the step's own estimate, the progress bar's numbers, and the
// counts. Pure functions of the status JSON, so that node can test them without a browser.
"use strict";

const StatusText = (() => {
  const ENDED = ["finished", "failed", "cancelled"];
  const PHASES = {
    queued: "queued",
    starting: "starting: the worker loads the mapper",
    tracking: "tracking",
    refining: "refining: the mapper takes in the last frames",
    writing: "writing outputs",
    done: "done",
  };
  // Each end-of-run step (slam.events.END_STEPS) says what it does.
  const STEPS = {
    bundle_adjustment: "refining: final bundle adjustment",
    retracking: "refining: re-tracking the frames against the final maps",
    colour_fit: "refining: fitting the fine colour",
    mesh: "refining: saving the map and extracting the mesh",
    outputs: "writing trajectories and run.json",
  };

  const plural = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;
  const clock = (seconds) => `${Math.floor(seconds / 60)}:${String(Math.floor(seconds % 60)).padStart(2, "0")}`;
  const centimetres = (metres) => `${(metres * 100).toFixed(2)} cm`;
  const inStep = (s) => (s.phase === "refining" || s.phase === "writing") && s.phase_step;

  function label(s) {
    return (inStep(s) && STEPS[s.phase_step]) || PHASES[s.phase] || s.phase;
  }

  // The step's estimate while it holds: past it, no bound is shown (it was an estimate).
  function withinEstimate(s) {
    return inStep(s) && s.phase_estimate_s != null && s.phase_elapsed_s != null &&
      s.phase_elapsed_s <= s.phase_estimate_s;
  }

  // What the session does now and for how long (the server's clock), against the step's
  // estimate while it holds; past it, that it takes longer, and no bound.
  function phase(s) {
    if (s.phase_elapsed_s == null) return label(s);
    const elapsed = `${label(s)} · ${clock(s.phase_elapsed_s)}`;
    if (withinEstimate(s)) return `${elapsed} of about ${clock(s.phase_estimate_s)}`;
    if (inStep(s) && s.phase_estimate_s != null) {
      return `${elapsed}, longer than its estimate of ${clock(s.phase_estimate_s)}: still working`;
    }
    return elapsed;
  }

  // The progress bar: {max, value} for a determinate bar, {} for a running (indeterminate)
  // one, null for none. Tracking counts frames; an end-of-run step its time against its
  // estimate while that holds.
  function progress(s) {
    if (s.phase === "tracking" && s.frames_total) return { max: s.frames_total, value: s.frames_done };
    if (s.phase !== "refining" && s.phase !== "writing") return null;
    if (withinEstimate(s) && s.phase_estimate_s > 0) {
      return { max: s.phase_estimate_s, value: Math.min(s.phase_elapsed_s, 0.99 * s.phase_estimate_s) };
    }
    return {};
  }

  function ate(s) {
    if (s.ate_rmse_m == null) return "";
    return ` · ATE ${centimetres(s.ate_rmse_m)}${ENDED.includes(s.status) ? "" : " so far"}`;
  }

  // Frames: a stream's sent / dropped / tracked (its clients' view and the session's),
  // otherwise tracked of the input's total.
  function frames(s) {
    if (s.frames_sent != null) {
      return `${s.frames_sent} sent · ${s.frames_dropped || 0} dropped · ${s.frames_done} tracked`;
    }
    const total = s.frames_total == null ? "" : ` / ${s.frames_total}`;
    return `${s.frames_done}${total} frames`;
  }

  // Colour from another camera: said when it was registered (given, or estimated and applied).
  function colour(s) {
    const text = s.color_camera || "";
    if (text.startsWith("given")) return " · colour registered (given camera)";
    if (text.includes(": applied")) return " · colour registered (camera estimated from the data)";
    return "";
  }

  function describe(s) {
    return `${frames(s)} · ${s.fps.toFixed(1)} frames/s · ${plural(s.keyframes, "keyframe")} · ` +
           `${plural(s.maps, "map")} · ${plural(s.loops, "loop")} · ${plural(s.agents || 1, "agent")}${ate(s)}` +
           colour(s);
  }

  return { ENDED, phase, progress, ate, describe, clock, plural, centimetres };
})();

if (typeof module !== "undefined") module.exports = StatusText;
