"""PackPilot."""

# Every compiled kernel of the package must be cached under the dependency-aware locator,
# whatever module a process imports first: register it before any kernel is defined.
import packpilot.jit as _jit  # noqa: F401
