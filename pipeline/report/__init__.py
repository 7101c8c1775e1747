"""Reports: a sweep's records -> tables (.md/.tex) and figures. No torch, no tracking imports."""
