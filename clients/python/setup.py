"""Generates the gRPC stubs from proto/loopd/v1/loopd.proto into loopd_client/_gen when the
package is built (pip install clients/python, pip wheel clients/python)."""
import os
import pathlib
import re

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent
PROTO_ROOT = pathlib.Path(os.environ.get("LOOPD_PROTO_DIR", HERE.parent.parent / "proto"))
PROTO = "loopd/v1/loopd.proto"


def generate(out: pathlib.Path) -> None:
    from grpc_tools import protoc

    include = pathlib.Path(protoc.__file__).parent / "_proto"
    if not (PROTO_ROOT / PROTO).exists():
        raise SystemExit(f"{PROTO_ROOT / PROTO} not found: build from the loopd repository or set LOOPD_PROTO_DIR")
    out.mkdir(parents=True, exist_ok=True)
    rc = protoc.main(["protoc", f"-I{PROTO_ROOT}", f"-I{include}", f"--python_out={out}",
                      f"--pyi_out={out}", f"--grpc_python_out={out}", str(PROTO_ROOT / PROTO)])
    if rc != 0:
        raise SystemExit(f"protoc failed on {PROTO} ({rc})")
    # protoc writes absolute imports (`from loopd.v1 import ...`); make them package-relative so
    # the stubs live inside loopd_client and cannot clash with another `loopd` module.
    grpc_file = out / "loopd/v1/loopd_pb2_grpc.py"
    text = re.sub(r"^from loopd\.v1 import", "from . import", grpc_file.read_text(), flags=re.M)
    grpc_file.write_text(text)
    for pkg in (out, out / "loopd", out / "loopd/v1"):
        (pkg / "__init__.py").touch()


class BuildWithStubs(build_py):
    def run(self):
        generate(pathlib.Path(self.build_lib) / "loopd_client/_gen")
        super().run()


setup(cmdclass={"build_py": BuildWithStubs})
