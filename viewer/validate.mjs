// Validate glb files with the Khronos glTF Validator; print one JSON report per file on stdout.
// usage: node validate.mjs FILE.glb [FILE.glb ...]
import { readFile } from 'node:fs/promises';
import validator from 'gltf-validator';

const MAX_MESSAGES = 20;
const reports = [];
for (const path of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(path));
  const report = await validator.validateBytes(bytes, {
    uri: path,
    maxIssues: 1000,
    externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}: glb content is self-contained`)),
  });
  const issues = report.issues;
  reports.push({
    path,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    hints: issues.numHints,
    messages: issues.messages.slice(0, MAX_MESSAGES).map((m) => ({ code: m.code, severity: m.severity, message: m.message, pointer: m.pointer })),
    extensionsUsed: report.info ? report.info.extensionsUsed : [],
  });
}
process.stdout.write(JSON.stringify(reports) + '\n');
