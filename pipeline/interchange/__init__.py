"""Files that travel and their readers: an episode's ``result.json`` and a preset's benchmark
definitions, their JSON Schemas and the checks that match one against the other; the typed records an
episode returns (``results``); a sweep folder's layout (``layout``) and its reader (``sweep_results``).
Torch-free (numpy, pandas, json and jsonschema), so reports, the viewer's listing and other codebases
read them without the pipeline's models."""
