// Replay a recording through the published champion, as a JavaScript simulator would:
//   node replay.mjs BUCKET_DIR ANGLE PUBLIC_KEY_BASE64 RECORDING.json [UNIT_ID]
// RECORDING.json: {"t_s": [...], "volts": [[v1, v2, v3], ...]}. Prints {"targets": ["fx", "fy", "fz"],
// "force_n": [[fx, fy, fz], ...], "calibrated": bool, "model": {...}} as JSON: a row per sample, a value per
// axis of the model's targets (those its reference recorded: {"targets": ["fz"], "force_n": [[fz], ...]}).
import { readFileSync } from "node:fs";

import { ForceModel, readManifest, readObject } from "./needlecue.mjs";

const [dir, angle, key, recordingPath, unitId] = process.argv.slice(2);
const model = await ForceModel.fromPublished(dir, `needle-force-${angle}`, "champion", key);
if (unitId) {
  const name = `needle-unit-${unitId}`;
  const manifest = readManifest(dir, name, "current", key);
  model.calibrate(JSON.parse(readObject(dir, manifest, "calibration.json").toString("utf8")));
}
const recording = JSON.parse(readFileSync(recordingPath, "utf8"));
const force = [];
for (let i = 0; i < recording.t_s.length; i++) force.push(await model.step(recording.volts[i], recording.t_s[i]));
const { kind, angle_deg, checkpoint_sha256 } = model.meta;
const out = { targets: model.targets, force_n: force, calibrated: model.calibrated, model: { kind, angle_deg, checkpoint_sha256 } };
console.log(JSON.stringify(out));
