"""Writes the hostile-spec corpus (``specs/*.yaml``): run ``python tests/hostile/make_corpus.py``.

Each file's first line is ``# expect: <text>``: the one-line error every command must print for it.
The files are committed; this script documents how each was made and regenerates them.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent

BASE = """\
name: hostile-base
seed: 0
simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}
dataset: {n: 20, batch_size: 5}
surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4]}
latent_models:
  flow: {type: realnvp, max_epochs: 2}
optimizers:
  cma: {type: cma_es, space: raw, budget: 20}
  gc: {type: gc_ppo, space: flow, total_timesteps: 64}
  warm: {type: warm_start, policy: gc}
objectives:
  firm: {weights: {peak_abs: 1.0, log_decay: 0.5}}
targets: {n: 2, validate: 1}
stages: [dataset, train, invert]
"""


def sub(old: str, new: str) -> str:
    assert old in BASE, old
    return BASE.replace(old, new, 1)


CASES: list[tuple[str, str | bytes, str]] = []


def case(name: str, text: str | bytes, expect: str) -> None:
    CASES.append((name, text, expect))


# -- YAML and file level -----------------------------------------------------------------------
case("empty", "", "a spec is a YAML mapping")
case("only-comments", "# nothing here\n", "a spec is a YAML mapping")
case("top-level-list", "- name: x\n- simulator: y\n", "a spec is a YAML mapping")
case("top-level-scalar", "just a string\n", "a spec is a YAML mapping")
case("top-level-number", "42\n", "a spec is a YAML mapping")
case("two-documents", BASE + "---\nname: second\n", "not valid YAML")
case("tab-indent", "name: x\nsimulator:\n\ttype: t\n", "not valid YAML")
case("unclosed-bracket", "name: [x\n", "not valid YAML")
case("unclosed-quote", 'name: "x\n', "not valid YAML")
case("bad-indent", "name: x\n  seed: 1\n simulator: y\n", "not valid YAML")
case("duplicate-top-key", BASE + "seed: 1\n", "key 'seed' appears twice")
case("duplicate-nested-key", sub("budget: 20}", "budget: 20, budget: 30}"), "key 'budget' appears twice")
case("duplicate-label", BASE.replace("  warm:", "  cma:"), "key 'cma' appears twice")
bomb = ["a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
bomb += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
case("alias-bomb", "\n".join(bomb) + "\n", "expands to more than")
case("alias-bomb-in-spec", BASE + "\n".join(bomb) + "\n", "expands to more than")
case("recursive-alias", "name: &n [1, *n]\n", "refers to the node that contains it")
case("deep-nesting", "name: " + "[" * 300 + "]" * 300 + "\n", "nested too deeply")
case("deep-mapping", "name: x\n" + "".join(f"{'  ' * i}k{i}:\n" for i in range(60)) + "  " * 60 + "v: 1\n",
     "nested too deeply")
case("python-object-tag", "name: !!python/object/apply:os.system ['echo pwned']\n", "not valid YAML")
case("python-name-tag", "name: !!python/name:os.system\n", "not valid YAML")
case("unknown-tag", "name: !custom x\n", "not valid YAML")
case("undefined-alias", "name: *nothing\n", "not valid YAML")
case("nul-byte", b"name: x\x00\nsimulator: {type: t}\n", "NUL byte on line 1")
case("latin1-bytes", "name: caf\xe9\n".encode("latin-1"), "not UTF-8 text")
case("utf16", BASE.encode("utf-16"), "not a text file")
case("control-char", "name: a\x07b\n", "not valid YAML")
case("binary-junk", bytes(range(256)) * 4, "not a text file")
case("non-string-key", sub("seed: 0\n", "seed: 0\n1: one\n"), "the key 1 is not text")
case("bool-key", sub("seed: 0\n", "seed: 0\non: 1\n"), "the key True is not text")
case("null-key", sub("seed: 0\n", "seed: 0\n~: 1\n"), "the key None is not text")
case("list-key", sub("seed: 0\n", "seed: 0\n? [a, b]\n: 1\n"), "not valid YAML")

# -- names that become paths -------------------------------------------------------------------
for i, label in enumerate(["../escape", "../../../../tmp/pwned", "/abs/path", "a/b", "..", ".", ".hidden",
                           "-rf", "x" * 65, "con", "NUL", "com1", "a b", "tab\tlabel", "naïve", "semi;colon",
                           "star*", "", "new\\nline", "back\\\\slash"]):
    quoted = '"' + label.replace('"', '\\"') + '"'
    case(f"label-optimizer-{i:02d}", sub("  cma: {type: cma_es", f"  {quoted}: {{type: cma_es"), "not a safe name")
case("label-latent", sub("  flow: {type: realnvp", '  "../flow": {type: realnvp').replace("space: flow", 'space: "../flow"'),
     "not a safe name")
case("label-objective", sub("  firm: {weights", '  "../../firm": {weights'), "not a safe name")
case("label-latent-long", sub("  flow: {type: realnvp", f"  {'f' * 200}: {{type: realnvp"), "longer than 64")
case("name-control-char", sub("name: hostile-base", 'name: "two\\nlines"'), "printable text on one line")
case("name-too-long", sub("name: hostile-base", "name: " + "n" * 201), "at most 200 characters")
case("name-empty", sub("name: hostile-base", 'name: ""'), "at least 1 character")

# -- non-finite numbers --------------------------------------------------------------------------
for i, (old, new) in enumerate([
        ("budget: 20}", "budget: 20, sigma0: .inf}"), ("budget: 20}", "budget: 20, sigma0: .nan}"),
        ("budget: 20}", "budget: 20, sigma0: -.inf}"), ("peak_abs: 1.0", "peak_abs: .nan"),
        ("peak_abs: 1.0", "peak_abs: .inf"), ("log_decay: 0.5", "log_decay: -.Inf"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {n: 20, batch_size: 5, test_fraction: .nan}"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {n: 20, batch_size: 5, limit_minutes: .inf}"),
        ("n_frames: 10}", "n_frames: 10, fps: .inf}"), ("n_frames: 10}", "n_frames: 10, sleep_s: .nan}"),
        ("max_epochs: 2,", "max_epochs: 2, lr: .nan,"), ("max_epochs: 2,", "max_epochs: 2, lr: .inf,"),
        ("seed: 0", "seed: .nan"), ("targets: {n: 2, validate: 1}", "targets: {n: .inf, validate: 1}"),
        ("hidden: [4, 4, 4]", "hidden: [4, .nan, 4]"), ("n_frames: 10}", "n_frames: 10, raise_c_above: .NaN}"),
]):
    case(f"nonfinite-{i:02d}", sub(old, new), "must be a finite number")

# -- types, ranges and absurd sizes --------------------------------------------------------------
for i, (old, new, expect) in enumerate([
        ("n: 20,", 'n: "twenty",', "dataset.n"), ("n: 20,", "n: 1.5,", "dataset.n"),
        ("n: 20,", "n: -5,", "must be > 0"), ("n: 20,", "n: 0,", "must be > 0"),
        ("n: 20,", "n: 1000000000000,", "must be <= 1000000"), ("batch_size: 5}", "batch_size: 0}", "must be > 0"),
        ("seed: 0", "seed: -1", "must be >= 0"), ("seed: 0", "seed: 99999999999999999999999", "must be <= "),
        ("stages: [dataset, train, invert]", "stages: dataset", "stages"),
        ("stages: [dataset, train, invert]", "stages: [dataset, trian]", "Did you mean 'train'"),
        ("stages: [dataset, train, invert]", "stages: [dataset, dataset]", "listed twice"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {n: 20, batch_size: 5, sampler: sobel}", "must be one of"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {n: 20, batch_size: 5, test_fraction: 1}", "must be < 1"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {n: 20, batch_size: 5, test_fraction: 0}", "must be > 0"),
        ('simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}', "simulator: toy",
         "simulator"),
        ('simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}', "simulator: {n_frames: 10}",
         "needs a 'type' field"),
        ('"test_dataset_toy:ToyOscillator"', "toy_osc", "No simulator named 'toy_osc'"),
        ('"test_dataset_toy:ToyOscillator"', '"os:system"', "simulator"),
        ('"test_dataset_toy:ToyOscillator"', '"no_such_module_xyz:Sim"', "cannot import module"),
        ('"test_dataset_toy:ToyOscillator"', '"test_dataset_toy:NoSuchClass"', "has no attribute"),
        ("n_frames: 10}", "n_frames: 1}", "must be >= 2"), ("n_frames: 10}", 'n_frames: "ten"}', "n_frames"),
        ("budget: 20}", "budget: 0}", "must be >= 1"), ("budget: 20}", "budget: twenty}", "budget"),
        ("type: cma_es", "type: cma_ess", "Did you mean 'cma_es'"), ("type: mlp", "type: mpl", "Did you mean 'mlp'"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 0, validate: 0}", "must be > 0"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 2, validate: -1}", "must be >= 0"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 2, selection: farthest}", "must be one of"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 99999999}", "must be <= 10000"),
        ("hidden: [4, 4, 4]", "hidden: [4, 4]", "hidden"), ("max_epochs: 2,", "max_epochs: -2,", "max_epochs"),
        ("objectives:\n  firm: {weights: {peak_abs: 1.0, log_decay: 0.5}}\n", "objectives:\n  firm: {weights: {}}\n",
         "weights"),
        ("objectives:\n  firm: {weights: {peak_abs: 1.0, log_decay: 0.5}}\n", "objectives: [firm]\n", "objectives"),
]):
    case(f"value-{i:02d}", sub(old, new), expect)

# -- unknown keys: did you mean ------------------------------------------------------------------
for i, (old, new, expect) in enumerate([
        ("optimizers:\n", "optimisers:\n", "Did you mean 'optimizers'"),
        ("dataset: {", "datset: {", "Did you mean 'dataset'"),
        ("targets: {", "target: {", "Did you mean 'targets'"),
        ("batch_size: 5}", "batchsize: 5}", "Did you mean 'batch_size'"),
        ("validate: 1}", "validat: 1}", "Did you mean 'validate'"),
        ("budget: 20}", "budjet: 20}", "Did you mean 'budget'"),
        ("n_frames: 10}", "nframes: 10}", "Did you mean 'n_frames'"),
        ("{weights:", "{wieghts:", "Did you mean 'weights'"),
        ("max_epochs: 2,", "max_epoch: 2,", "Did you mean 'max_epochs'"),
        ("seed: 0", "sead: 0", "Did you mean 'seed'"),
]):
    case(f"unknown-key-{i:02d}", sub(old, new), expect)

# -- cross-references known without training -----------------------------------------------------
for i, (old, new, expect) in enumerate([
        ("peak_abs: 1.0", "peak_abz: 1.0", "no feature 'peak_abz'. Did you mean 'peak_abs'"),
        ("log_decay: 0.5", "stiffness: 0.5", "no feature 'stiffness'"),
        ("warm: {type: warm_start, policy: gc}", "warm: {type: warm_start}", "needs `policy:"),
        ("warm: {type: warm_start, policy: gc}", "warm: {type: warm_start, policy: cma}", "'cma' is not a goal-conditioned"),
        ("warm: {type: warm_start, policy: gc}", "warm: {type: warm_start, policy: gcc}", "Did you mean 'gc'"),
        ("warm: {type: warm_start, policy: gc}", "warm: {type: warm_start, policy_path: no/such/dir}", "no saved policy"),
        ("space: flow", "space: flw", "neither 'raw' nor a latent model label"),
        ("space: raw, budget: 20}", "space: raw, budget: 20, evaluator: mine}", "must be 'shared' or 'own_head'"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 5, validate: 1}", "held-out split has at most 4"),
        ("targets: {n: 2, validate: 1}", "targets: {n: 2, validate: 3}", "3 targets to validate"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {path: no/such/store}", "no dataset at 'no/such/store'"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {path: ../../../../../../../../etc/passwd}", "is a file"),
        ("dataset: {n: 20, batch_size: 5}", "dataset: {path: /etc}", "not an invphys dataset"),
        ("surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4]}\n", "", "needs a 'surrogate' section"),
        ("stages: [dataset, train, invert]", "stages: [dataset, train, invert]\nvalidator: null\n"
         "report: {formats: [pdf]}", "must be one of"),
]):
    case(f"reference-{i:02d}", sub(old, new), expect)

# -- what validate knows, run will not refuse later (issue 47): targets read against the features ---------
for name, new, expect in [
    ("targets-unknown-feature", "targets: {values: [{peek_abs: 1.0}]}", "unknown feature 'peek_abs'. Did you mean 'peak_abs'?"),
    ("targets-not-a-number", "targets: {values: [{peak_abs: lots}]}", "peak_abs = 'lots' is not a number"),
    ("targets-file-missing", "targets: {file: no/such/targets.csv}", "'no/such/targets.csv' is absent"),
    ("targets-file-directory", "targets: {file: /etc}", "'/etc' is a directory"),
    ("targets-file-device", "targets: {file: /dev/zero}", "'/dev/zero' is not a regular file"),
    ("targets-huge-integer", "targets: {values: [{peak_abs: " + "9" * 400 + "}]}", "too large for a number"),
    ("seed-huge-integer", None, "too large for a number"),
]:
    text = sub("seed: 0", "seed: " + "7" * 450) if new is None else sub("targets: {n: 2, validate: 1}", new)
    case(f"validate-{name}", text, expect)


def main() -> None:
    out = HERE / "specs"
    out.mkdir(exist_ok=True)
    for old in out.glob("*.yaml"):
        old.unlink()
    for i, (name, text, expect) in enumerate(CASES):
        header = f"# expect: {expect}\n".encode()
        body = text if isinstance(text, bytes) else text.encode()
        (out / f"{i:03d}-{name}.yaml").write_bytes(body if name in _RAW else header + body)
        if name in _RAW:
            (out / f"{i:03d}-{name}.expect").write_text(expect + "\n")
    print(f"{len(CASES)} hostile specs in {out}")


#: cases whose bytes must stay exactly as made (no header line): their expectation is in a .expect file
_RAW = {"utf16", "binary-junk", "empty", "nul-byte", "latin1-bytes"}

if __name__ == "__main__":
    main()
