"""TorchScript descriptor models for loopd (docs/models.md), made here with the venv's torch.

No pretrained place-recognition weights can be downloaded on the project's machines, so these
are small residual networks with seeded random weights: what they compute is meaningless for
places, but it is a real PyTorch model that loopd must run exactly as PyTorch does. The export
part is also the worked example docs/models.md points to.

usage:
  script_models.py export OUT
      writes OUT/small-resnet (RGB, torchvision normalisation, 512-d, not normalised),
      OUT/small-bgr (BGR, caffe means, aspect kept, 256-d, normalised by the model), and
      broken ones: OUT/wrong-dim (the manifest says 128, the model gives 512) and OUT/nan.
  script_models.py reference WEIGHTS OUT
      writes OUT/reference: the independent PyTorch implementation of loopd's own network
      (reference.py: ResNet50, attention, fusion; identity heads) on a loopd weight file, traced
      to TorchScript with its weights inside, input as loopd's built-in network takes it (224x224
      stretched, caffe: BGR minus the ImageNet mean), 2048-d, normalised.
  script_models.py compare MODEL_DIR SAVED_DIR
      SAVED_DIR: what `loopd models check MODEL_DIR --save SAVED_DIR` wrote (per image: the
      resized RGB, loopd's input and loopd's descriptor). Recomputes the input from the RGB by
      the manifest and the descriptor with PyTorch from loopd's input; prints the largest
      differences as JSON and exits 1 if one is above 1e-5.
"""
import json
import os
import shutil
import sys

import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.torch import load_file

TOL = 1e-5


class Block(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = nn.Sequential()
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + self.down(x))


class SmallResNet(nn.Module):
    """A ResNet18-shaped network at a quarter of its width, global average pooled, projected."""

    def __init__(self, dim: int, normalize: bool):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, 16, 7, 2, 3, bias=False), nn.BatchNorm2d(16), nn.ReLU(),
                                  nn.MaxPool2d(3, 2, 1))
        widths = [16, 32, 64, 128]
        layers = []
        cin = 16
        for i, w in enumerate(widths):
            layers += [Block(cin, w, 1 if i == 0 else 2), Block(w, w, 1)]
            cin = w
        self.layers = nn.Sequential(*layers)
        self.proj = nn.Linear(cin, dim)
        self.normalize = normalize

    def forward(self, x):
        y = self.layers(self.stem(x))
        y = self.proj(y.mean(dim=(2, 3)))
        if self.normalize:
            y = F.normalize(y, dim=1)
        return y


class NotFinite(nn.Module):
    def forward(self, x):
        return torch.full((x.shape[0], 8), float("nan"))


def seeded(dim, normalize, seed):
    torch.manual_seed(seed)
    net = SmallResNet(dim, normalize)
    # Batch-norm statistics that are not the identity, so they matter.
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.uniform_(0.8, 1.2)
                m.bias.uniform_(-0.1, 0.1)
    return net.eval()


def save(out, name, module, manifest):
    d = os.path.join(out, name)
    os.makedirs(d, exist_ok=True)
    torch.jit.save(torch.jit.script(module), os.path.join(d, "model.pt"))
    with open(os.path.join(d, "model.json"), "w") as f:
        json.dump(dict(name=name, **manifest), f, indent=2)
    return d


def export(out):
    license_text = "test model made by tests/reference/script_models.py (seeded random weights)"
    save(out, "small-resnet", seeded(512, False, 1), {
        "input": {"width": 320, "height": 240},
        "output_dim": 512, "normalized": False, "license": license_text, "source": "loopd tests"})
    save(out, "small-bgr", seeded(256, True, 2), {
        "input": {"width": 288, "height": 288, "resize": "keep", "channels": "bgr", "scale": 1.0,
                  "mean": [103.939, 116.779, 123.68], "std": [1.0, 1.0, 1.0]},
        "output_dim": 256, "normalized": True, "license": license_text, "source": "loopd tests"})
    wrong = os.path.join(out, "wrong-dim")
    shutil.copytree(os.path.join(out, "small-resnet"), wrong)
    with open(os.path.join(wrong, "model.json")) as f:
        m = json.load(f)
    m.update(name="wrong-dim", output_dim=128)
    with open(os.path.join(wrong, "model.json"), "w") as f:
        json.dump(m, f)
    save(out, "nan", NotFinite(), {"input": {"width": 64, "height": 64}, "output_dim": 8})


class Reference(nn.Module):
    """reference.py's descriptor (attention and fusion on) with a weight file's tensors as buffers."""

    def __init__(self, weights, v1):
        super().__init__()
        self.names = sorted(weights)
        for i, k in enumerate(self.names):
            self.register_buffer(f"w{i}", weights[k])
        self.v1 = v1

    def forward(self, x):
        import reference
        w = {k: getattr(self, f"w{i}") for i, k in enumerate(self.names)}
        return reference.descriptor(w, x, True, True, self.v1)


def export_reference(weights, out):
    from safetensors import safe_open
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    w = {k: t.float() for k, t in load_file(weights).items()}
    with safe_open(weights, "pt") as f:
        meta = f.metadata() or {}
    if meta.get("normalization", "caffe") != "caffe":
        raise SystemExit(f"{weights}: normalization {meta.get('normalization')}, this export writes caffe inputs")
    net = Reference(w, meta.get("stride_layout", "v1") == "v1").eval()
    d = os.path.join(out, "reference")
    os.makedirs(d, exist_ok=True)
    with torch.no_grad():
        traced = torch.jit.trace(net, torch.zeros(1, 3, 224, 224))
    torch.jit.save(traced, os.path.join(d, "model.pt"))
    manifest = {"name": "reference", "input": {"width": 224, "height": 224, "channels": "bgr", "scale": 1.0,
                                               "mean": [103.939, 116.779, 123.68], "std": [1.0, 1.0, 1.0]},
                "output_dim": 2048, "normalized": True,
                "license": "the weight file's", "source": "tests/reference/reference.py, traced"}
    with open(os.path.join(d, "model.json"), "w") as f:
        json.dump(manifest, f, indent=2)


def compare(model_dir, saved_dir):
    with open(os.path.join(model_dir, "model.json")) as f:
        m = json.load(f)
    inp = m["input"]
    scale = inp.get("scale", 1.0 / 255.0)
    mean = torch.tensor(inp.get("mean", [0.485, 0.456, 0.406]), dtype=torch.float32).reshape(3, 1, 1)
    std = torch.tensor(inp.get("std", [0.229, 0.224, 0.225]), dtype=torch.float32).reshape(3, 1, 1)
    module = torch.jit.load(os.path.join(model_dir, m.get("file", "model.pt"))).eval()
    report = {}
    for name in sorted(os.listdir(saved_dir)):
        t = load_file(os.path.join(saved_dir, name))
        rgb = t["rgb"]
        x = rgb.flip(0) if inp.get("channels", "rgb") == "bgr" else rgb
        x = (x * scale - mean) / std
        with torch.no_grad():
            d = F.normalize(module(t["input"][None]).float(), dim=1)[0]
        report[name] = {
            "input_max_abs_diff": float((x - t["input"]).abs().max()),
            "descriptor_max_abs_diff": float((d - t["descriptor"]).abs().max()),
            "dim": int(d.numel()),
        }
    print(json.dumps(report))
    worst = max(max(r["input_max_abs_diff"], r["descriptor_max_abs_diff"]) for r in report.values())
    return 0 if report and worst <= TOL else 1


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "export":
        export(sys.argv[2])
        sys.exit(0)
    if len(sys.argv) == 4 and sys.argv[1] == "reference":
        export_reference(sys.argv[2], sys.argv[3])
        sys.exit(0)
    if len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(compare(sys.argv[2], sys.argv[3]))
    print(__doc__)
    sys.exit(2)
