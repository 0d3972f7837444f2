#!/usr/bin/env node
// Validates a .glb/.gltf file with the Khronos glTF validator (npm package gltf-validator).
// Usage: node tools/validate_gltf.mjs FILE [--max-issues N]
// Prints the validator's JSON report to stdout; exits 1 if it has errors, 2 on bad usage or I/O.
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";

const args = process.argv.slice(2);
const file = args.find((a) => !a.startsWith("--"));
const maxIndex = args.indexOf("--max-issues");
const maxIssues = maxIndex >= 0 ? Number(args[maxIndex + 1]) : 0; // 0: unlimited
if (!file || Number.isNaN(maxIssues)) {
  console.error("usage: node tools/validate_gltf.mjs FILE [--max-issues N]");
  process.exit(2);
}

let data;
try {
  data = new Uint8Array(await readFile(file));
} catch (err) {
  console.error(`cannot read ${file}: ${err.message}`);
  process.exit(2);
}

try {
  const report = await validator.validateBytes(data, {
    uri: path.basename(file),
    maxIssues,
    writeTimestamp: false,
  });
  process.stdout.write(JSON.stringify(report, null, 2) + "\n");
  process.exit(report.issues.numErrors > 0 ? 1 : 0);
} catch (err) {
  // The validator rejects when it cannot even detect the format (not glTF/GLB).
  console.error(`validation failed: ${err}`);
  process.exit(2);
}
