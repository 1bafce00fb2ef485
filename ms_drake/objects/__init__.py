"""Object sets: procedural shapes and converted mesh datasets (see registry.py)."""

from ms_drake.objects.registry import (  # noqa: F401
    TARGET_RGBA,
    ObjectSet,
    ObjectSpec,
    available_sets,
    get_object,
    get_object_set,
)
