"""The public API's surface as text: each name's kind and signature, each public method's too."""

from __future__ import annotations

import dataclasses
import inspect


def surface(module) -> dict[str, str]:
    out = {}
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isclass(obj):
            fields = ([f"{f.name}: {f.type}" for f in dataclasses.fields(obj)] if dataclasses.is_dataclass(obj)
                      else [])
            out[name] = f"class({', '.join(fields)})"
            for attr, member in sorted(vars(obj).items()):
                if attr.startswith("_") or not (inspect.isfunction(member) or isinstance(member, (classmethod, property))):
                    continue
                fn = member.__func__ if isinstance(member, classmethod) else member
                out[f"{name}.{attr}"] = ("property" if isinstance(member, property)
                                         else str(inspect.signature(fn)))
        elif callable(obj):
            out[name] = str(inspect.signature(obj))
        else:
            out[name] = repr(obj)
    return out
