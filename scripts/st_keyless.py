"""A schemathesis check for the run without a key (scripts/e2e): every operation but health
answers 401. Loaded with SCHEMATHESIS_HOOKS=scripts.st_keyless."""
import schemathesis

OPEN = {"/healthz", "/readyz"}


@schemathesis.check
def refused_without_a_key(ctx, response, case):
    if case.operation.path in OPEN:
        return None
    if response.status_code != 401:
        raise AssertionError(
            f"{case.method} {case.formatted_path} answered {response.status_code} without a key (expected 401)")
    return None
