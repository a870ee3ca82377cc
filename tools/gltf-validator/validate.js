#!/usr/bin/env node
// Validate glTF files with the Khronos glTF validator (the pinned npm package in this folder) and print the report
// of each as one JSON line: {"file", "report"} (the validator's own report object) or {"file", "error"}.
//   node tools/gltf-validator/validate.js FILE.glb [FILE ...] [--max-issues N]
// Exit status: 0 when every file was validated (whatever the issues), 2 on bad arguments, 1 when a file could not be
// read or the validator refused it. Deciding which issues are acceptable is the caller's job.
"use strict";
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

async function main(argv) {
  let maxIssues = 1000;
  const files = [];
  for (let i = 0; i < argv.length; i++) {
    if (argv[i] === "--max-issues") {
      maxIssues = Number(argv[++i]);
      if (!Number.isInteger(maxIssues) || maxIssues < 0) {
        console.error("validate.js: --max-issues takes a whole number");
        return 2;
      }
    } else {
      files.push(argv[i]);
    }
  }
  if (!files.length) {
    console.error("usage: node validate.js FILE.glb [FILE ...] [--max-issues N]");
    return 2;
  }
  let status = 0;
  for (const file of files) {
    try {
      const bytes = new Uint8Array(fs.readFileSync(file));
      const report = await validator.validateBytes(bytes, {
        uri: path.basename(file),
        maxIssues,
        // a .gltf beside its resources; a .glb needs none
        externalResourceFunction: (uri) =>
          fs.promises.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))),
      });
      console.log(JSON.stringify({ file, report }));
    } catch (e) {
      console.log(JSON.stringify({ file, error: String(e && e.message || e) }));
      status = 1;
    }
  }
  return status;
}

main(process.argv.slice(2)).then((code) => { process.exitCode = code; });
