"""Bridges between splatzoo and other tools' frameworks. Each lives in a subpackage that imports its tool only when
its own modules are used: `splatzoo.integrations.nerfstudio` (ns-train methods and the reader of their outputs)."""
