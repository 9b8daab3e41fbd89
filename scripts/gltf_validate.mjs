#!/usr/bin/env node
// Validate glb/glTF files with the Khronos glTF Validator (npm package gltf-validator).
//
//   node scripts/gltf_validate.mjs [--max-messages N] FILE...   one JSON report a line for each FILE: its numbers of
//       errors, warnings, infos and hints, its first N messages (20; 0: all), errors first, and the validator's info
//   node scripts/gltf_validate.mjs --version                     the validator's version
//
// The validator is looked up in $ANISDF_GLTF_VALIDATOR (a node_modules folder) or else in .ci/node/node_modules of
// this repository (`make gltf-validator` installs it there); nothing is downloaded here.
// Exit status: 0 when no file has errors, 1 when one has (or could not be read or parsed), 2 when the validator is
// not installed or the arguments are wrong. A file that cannot be read or parsed is reported with numErrors 1 and
// its failure.
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const modules = process.env.ANISDF_GLTF_VALIDATOR || join(here, "..", ".ci", "node", "node_modules");
const SEVERITY = ["error", "warning", "info", "hint"];

function loadValidator() {
  try {
    return createRequire(import.meta.url)(resolve(modules, "gltf-validator"));
  } catch (err) {
    const where = process.env.ANISDF_GLTF_VALIDATOR ? " ($ANISDF_GLTF_VALIDATOR)" : ": install it with `make gltf-validator`";
    console.error(`gltf-validator not found in ${resolve(modules)}${where} (${err.code || err})`);
    process.exit(2);
  }
}

const args = process.argv.slice(2);
let maxMessages = 20;
const files = [];
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--version") {
    console.log(loadValidator().version());
    process.exit(0);
  } else if (args[i] === "--max-messages" && i + 1 < args.length) {
    maxMessages = Number(args[++i]);
  } else if (args[i].startsWith("-")) {
    console.error(`unknown option ${args[i]}`);
    process.exit(2);
  } else {
    files.push(args[i]);
  }
}
if (files.length === 0 || !Number.isInteger(maxMessages) || maxMessages < 0) {
  console.error("usage: gltf_validate.mjs [--max-messages N] FILE...");
  process.exit(2);
}

function brief(m) {
  const out = { code: m.code, severity: SEVERITY[m.severity] ?? m.severity, message: m.message };
  if (m.pointer !== undefined) out.pointer = m.pointer;
  if (m.offset !== undefined) out.offset = m.offset;
  return out;
}

const validator = loadValidator();
let failed = false;
for (const file of files) {
  const out = { file, validatorVersion: validator.version() };
  try {
    const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
      uri: file, maxIssues: 0, writeTimestamp: false,
    });
    const issues = report.issues;
    Object.assign(out, {
      numErrors: issues.numErrors, numWarnings: issues.numWarnings, numInfos: issues.numInfos,
      numHints: issues.numHints, truncated: issues.truncated,
      messages: [...issues.messages].sort((a, b) => a.severity - b.severity)  // errors first (a stable sort)
        .slice(0, maxMessages || undefined).map(brief),
      info: report.info,
    });
    failed ||= issues.numErrors > 0;
  } catch (err) {  // unreadable file, or bytes the validator cannot take as glTF or GLB
    Object.assign(out, { numErrors: 1, failure: String(err) });
    failed = true;
  }
  console.log(JSON.stringify(out));
}
process.exit(failed ? 1 : 0);
