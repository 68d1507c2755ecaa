"""A schemathesis check for the run without a key (scripts/e2e): every operation but health and
the loop inspector's static page and files (they hold no data) answers 401. Loaded with
SCHEMATHESIS_HOOKS=scripts.st_keyless."""
import schemathesis

OPEN = {"/healthz", "/readyz", "/v1/sessions/{id}/inspect", "/v1/inspector/app.js", "/v1/inspector/app.css"}


@schemathesis.check
def refused_without_a_key(ctx, response, case):
    if case.operation.path in OPEN:
        return None
    if response.status_code != 401:
        raise AssertionError(
            f"{case.method} {case.formatted_path} answered {response.status_code} without a key (expected 401)")
    return None
