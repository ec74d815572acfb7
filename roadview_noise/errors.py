"""Error tree. Every error names the file and the field it is about, so a user can fix the input."""

from __future__ import annotations


class RvNoiseError(ValueError):
    """Base of every error rvnoise raises on purpose."""


class RecipeError(RvNoiseError):
    """A recipe is invalid: names the recipe file and the key path."""

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None):
        self.file, self.key, self.message = file, key, message
        where = ": ".join(p for p in (file, key) if p)
        super().__init__(f"{where}: {message}" if where else message)


class InputError(RvNoiseError):
    """An input file cannot be read or is inconsistent: names the file and the problem."""

    def __init__(self, message: str, *, file: str | None = None):
        self.file = file
        super().__init__(f"{file}: {message}" if file else message)


class EmptyCloudError(InputError):
    """A point cloud with no point to augment (0 points, or only the all-NaN point that marks an empty frame, as in
    nuScenes' radar sweeps without detections): ``augment`` writes it unchanged."""


class ModelError(RvNoiseError):
    """A model was given parameters or data it cannot work with: names the model and the field."""

    def __init__(self, message: str, *, model: str | None = None, field: str | None = None):
        self.model, self.field = model, field
        where = ".".join(p for p in (model, field) if p)
        super().__init__(f"{where}: {message}" if where else message)


class OutputError(RvNoiseError):
    """The output folder cannot be used (a file, not writable, locked by another run, holds another recipe's run)."""
