"""Files that travel: an episode's ``result.json`` and a preset's benchmark definitions, their
JSON Schemas, and the checks that match one against the other. Torch-free (numpy, json and
jsonschema only), so reports and other codebases read them without the pipeline's models."""
