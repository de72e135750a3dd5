// A needlecue force model outside Python: the published champion, verified, run by onnxruntime for
// Node.js, sample by sample, as a simulator in JavaScript would (docs/deploy.md is the contract).
//
// The published bucket is read from a local copy (`aws s3 sync s3://published DIR`, or any S3 client):
// manifests/<name>/<alias>.json, signed by the lab, and objects/sha256/<hex>, the files it names.

import { createHash, createPublicKey, verify } from "node:crypto";
import { readFileSync } from "node:fs";
import { join } from "node:path";

import yaml from "js-yaml";
import ort from "onnxruntime-node";

export const PUBLISHED_FORMAT = "needlecue-published/1";
export const DEPLOY_FORMAT = "needlecue-deploy/4";
export const INPUT_NAMES = ["reading", "rest_reading", "volts_per_count", "unit_matrix", "unit_offset", "unit_circuit"];
export const AXES = ["fx", "fy", "fz"]; // the force axes a model may give: its `targets` are some of them, in this order
const ED25519_SPKI = Buffer.from("302a300506032b6570032100", "hex"); // DER prefix of a raw Ed25519 key

/** JSON with sorted keys and no spaces: the bytes the lab's signature covers. */
export function canonical(value) {
  if (Array.isArray(value)) return `[${value.map(canonical).join(",")}]`;
  if (value !== null && typeof value === "object") {
    const keys = Object.keys(value).sort();
    return `{${keys.map((k) => `${JSON.stringify(k)}:${canonical(value[k])}`).join(",")}}`;
  }
  return JSON.stringify(value);
}

function sha256(bytes) {
  return createHash("sha256").update(bytes).digest("hex");
}

/** The manifest of `name@alias` in the bucket copy `dir`, once the lab's signature holds. */
export function readManifest(dir, name, alias, publicKeyBase64) {
  const where = join(dir, "manifests", name, `${alias}.json`);
  const doc = JSON.parse(readFileSync(where, "utf8"));
  const key = createPublicKey({
    key: Buffer.concat([ED25519_SPKI, Buffer.from(publicKeyBase64, "base64")]),
    format: "der",
    type: "spki",
  });
  const body = doc.manifest;
  const signed = Buffer.from(canonical(body), "utf8");
  if (typeof doc.signature !== "string" || !verify(null, signed, key, Buffer.from(doc.signature, "base64"))) {
    throw new Error(`${where}: refused, not signed by the lab's key (or changed after signing)`);
  }
  if (body.format !== PUBLISHED_FORMAT) throw new Error(`${where}: format ${body.format}, expected ${PUBLISHED_FORMAT}`);
  if (body.name !== name || body.alias !== alias) {
    throw new Error(`${where}: the manifest is ${body.name}@${body.alias}, not ${name}@${alias}`);
  }
  return body;
}

/** The bytes of one file the manifest names, checked against its sha256 and size. */
export function readObject(dir, manifest, file) {
  const entry = manifest.files[file];
  if (!entry) throw new Error(`${manifest.name}@${manifest.alias}: the manifest names no ${file}`);
  const bytes = readFileSync(join(dir, "objects", "sha256", entry.sha256));
  if (sha256(bytes) !== entry.sha256 || bytes.length !== entry.size) {
    throw new Error(`objects/sha256/${entry.sha256} (${file}): its bytes are not the manifest's`);
  }
  return bytes;
}

/** A unit's circuit as the graph's six numbers: [circuit, a, b, series_kohm, offset_v, on_conductance]. */
export function encodeCircuit(frontEnd, onConductance) {
  const flag = onConductance ? 1 : 0;
  if (!frontEnd || frontEnd.circuit === "none") return [0, 0, 0, 0, 0, flag];
  const series = frontEnd.series_kohm ?? 0;
  if (frontEnd.circuit === "divider") {
    const code = (frontEnd.fsr_at ?? "supply") === "supply" ? 1 : 2;
    return [code, frontEnd.supply_v, frontEnd.fixed_kohm, series, 0, flag];
  }
  if (frontEnd.circuit === "transimpedance") {
    return [3, frontEnd.drive_v, frontEnd.feedback_kohm, series, frontEnd.offset_v ?? 0, flag];
  }
  throw new Error(`unknown circuit ${JSON.stringify(frontEnd.circuit)}`);
}

function angleName(deg) {
  // the keys of a calibration's models, as Python's f"{deg:g}": 30 -> "30", 22.5 -> "22.5", -0 -> "0"
  return String(Number((deg + 0).toPrecision(6)));
}

/** The description's `targets`, checked: the force axes the model gives, one graph column each, a
 * non-empty subset of fx, fy, fz in that order (those its reference recorded: ["fz"] from a load cell). */
export function targetsOf(meta, name = "the model") {
  const t = meta.targets;
  const ok = Array.isArray(t) && t.length > 0 && canonical(t) === canonical(AXES.filter((a) => t.includes(a)));
  if (!ok) {
    throw new Error(
      `${name}: field needlecue.targets is ${JSON.stringify(t)}; expected a non-empty list of force axes among ${AXES.join(", ")}, in that order`,
    );
  }
  return [...t];
}

/** One force model, run one estimator sample at a time (`step`); `reset()` between insertions.
 * `voltsPerCount`: 1 when `step` gets volts; vref / (2^bits - 1) when it gets the ADC's counts.
 * `targets`: the axes of `step`'s force, in its order (["fx", "fy", "fz"], or ["fz"] for a model of fz). */
export class ForceModel {
  constructor(session, meta, voltsPerCount = 1) {
    this.session = session;
    this.meta = meta;
    this.targets = targetsOf(meta);
    this.voltsPerCount = Float64Array.of(voltsPerCount);
    this.channels = meta.channels;
    this.window = meta.window;
    this.restS = (meta.inputs ?? {}).rest_s ?? 0.5;
    this.n = this.channels.length;
    this.calibrated = false;
    this.uncalibrate();
    this.reset();
  }

  /** The model of `name@alias` from a bucket copy: manifest signature, file hashes, graph hash. */
  static async fromPublished(dir, name, alias, publicKeyBase64, voltsPerCount = 1) {
    const manifest = readManifest(dir, name, alias, publicKeyBase64);
    const meta = yaml.load(readObject(dir, manifest, "MLmodel").toString("utf8")).metadata.needlecue;
    const graph = readObject(dir, manifest, "model.onnx");
    if (meta.format !== DEPLOY_FORMAT) throw new Error(`${name}: a ${meta.format} model; this client runs ${DEPLOY_FORMAT}`);
    if (sha256(graph) !== meta.onnx_sha256) throw new Error(`${name}: model.onnx is not the graph its MLmodel names`);
    if (canonical(meta.graph_inputs) !== canonical(INPUT_NAMES)) throw new Error(`${name}: unexpected graph inputs`);
    targetsOf(meta, name);
    const session = await ort.InferenceSession.create(graph, { intraOpNumThreads: 1, interOpNumThreads: 1 });
    return new ForceModel(session, meta, voltsPerCount);
  }

  uncalibrate() {
    const eye = new Float64Array(this.n * this.n);
    for (let i = 0; i < this.n; i++) eye[i * this.n + i] = 1;
    this.unit = { matrix: eye, offset: new Float64Array(this.n), circuit: Float64Array.from(encodeCircuit(null, false)) };
    this.calibrated = false;
  }

  /** Apply a unit's calibration document (calibration.json) if it was made with this very model;
   * returns whether it applies (else the unit stays uncalibrated: force without calibration). */
  calibrate(doc) {
    const t = (doc.transforms ?? {})[this.meta.kind];
    const made = t?.models?.[angleName(this.meta.angle_deg)];
    if (!t || made !== this.meta.checkpoint_sha256) {
      this.uncalibrate();
      return false;
    }
    const domain = t.domain ?? "inputs";
    if (domain !== "inputs" && domain !== "conductance") throw new Error(`calibration: unknown domain ${domain}`);
    const onConductance = domain === "conductance";
    const flat = t.matrix.flat();
    if (t.matrix.length !== this.n || flat.length !== this.n * this.n || t.offset.length !== this.n) {
      throw new Error(`calibration: a ${this.n} x ${this.n} matrix and ${this.n} offsets expected`);
    }
    if (![...flat, ...t.offset].every(Number.isFinite)) throw new Error("calibration: non-finite numbers");
    if (onConductance && (!doc.front_end || doc.front_end.circuit === "none")) {
      throw new Error("calibration: a map of the conductance needs the unit's declared circuit (front_end)");
    }
    this.unit = {
      matrix: Float64Array.from(flat),
      offset: Float64Array.from(t.offset),
      circuit: Float64Array.from(encodeCircuit(doc.front_end, onConductance)),
    };
    this.calibrated = true;
    return true;
  }

  reset() {
    this.frames = 0;
    this.volts = new Float64Array(this.window * this.n);
    this.rests = new Float64Array(this.window * this.n);
    this.restSum = new Float64Array(this.n);
    this.restCount = 0;
    this.restFrozen = false;
    this.t0 = null;
  }

  _slide(buffer, sample) {
    if (this.frames === 0) {
      for (let w = 0; w < this.window; w++) buffer.set(sample, w * this.n); // the first sample fills it
    } else {
      buffer.copyWithin(0, this.n);
      buffer.set(sample, (this.window - 1) * this.n);
    }
  }

  /** One sample (readings in `channels` order) at time `t` (s) -> the force in N, one value per axis of
   * `targets`, in that order ([fx, fy, fz], or [fz] for a model of fz alone). */
  async step(volts, t) {
    if (volts.length !== this.n) throw new Error(`step takes ${this.n} readings (${this.channels.join(", ")})`);
    if (!Number.isFinite(t) || !Array.from(volts).every(Number.isFinite)) {
      throw new Error(`step needs a finite time (s) and finite readings, got t=${t}, [${Array.from(volts)}]`);
    }
    if (this.t0 === null) this.t0 = t;
    if (!this.restFrozen && t - this.t0 < this.restS - 1e-9) {
      for (let c = 0; c < this.n; c++) this.restSum[c] += volts[c];
      this.restCount += 1;
    } else {
      this.restFrozen = true;
    }
    const rest = Float64Array.from(this.restSum, (s) => s / this.restCount);
    this._slide(this.volts, volts);
    this._slide(this.rests, rest);
    this.frames += 1;
    const shape = [1, this.window, this.n];
    const feed = {
      reading: new ort.Tensor("float64", this.volts, shape),
      rest_reading: new ort.Tensor("float64", this.rests, shape),
      volts_per_count: new ort.Tensor("float64", this.voltsPerCount, [1]),
      unit_matrix: new ort.Tensor("float64", this.unit.matrix, [this.n, this.n]),
      unit_offset: new ort.Tensor("float64", this.unit.offset, [this.n]),
      unit_circuit: new ort.Tensor("float64", this.unit.circuit, [6]),
    };
    const out = await this.session.run(feed);
    const force = Array.from(out[this.meta.output].data);
    if (force.length !== this.targets.length) {
      throw new Error(`the graph gave ${force.length} force values, its description names ${this.targets.join(", ")}`);
    }
    return force;
  }
}
