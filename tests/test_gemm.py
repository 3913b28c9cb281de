"""The learner's portable GEMMs (mam_core/gemm.py): right, the same bits for any thread count, and,
in pinned OpenBLAS (MAM_PORTABLE_GEMM=openblas), never in the form OpenBLAS runs with another
kernel on AVX-512 CPUs. The default kernels' own tests: tests/test_chain_gemm.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from mam_core import arithmetic, gemm
from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_lab.bench_learner import random_replay
from tests.e2e import ROOT

pytestmark = pytest.mark.skipif(not arithmetic.portable_gemm(), reason="the suite runs with portable arithmetic")


@pytest.fixture(autouse=True)
def one_thread():
    gemm.set_threads(1)  # another test of this process may have left more (chaos.compare_with_fault_free)
    yield
    gemm.set_threads(1)


@pytest.fixture
def openblas(monkeypatch: pytest.MonkeyPatch) -> None:
    """The products in pinned OpenBLAS (MAM_PORTABLE_GEMM=openblas) in this process."""
    monkeypatch.setattr(gemm, "_chain", lambda: None)
    gemm.set_threads(2)  # the pool as set_threads makes it for OpenBLAS (none while its batch call is there)
    gemm.set_threads(1)


def layouts(e: int, m: int, k: int, n: int, rng: np.random.Generator) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(a, b) pairs of one product in every layout the layers make: row- and column-major operands,
    a member axis expanded from one shared input."""
    a = torch.from_numpy(rng.standard_normal((e, m, k), dtype=np.float32))
    b = torch.from_numpy(rng.standard_normal((e, k, n), dtype=np.float32))
    shared = torch.from_numpy(rng.standard_normal((k, n), dtype=np.float32)).unsqueeze(0).expand(e, -1, -1)
    return [(a, b), (a.mT.contiguous().mT, b), (a, b.mT.contiguous().mT), (a.mT.contiguous().mT, b.mT.contiguous().mT),
            (a, shared), (a, shared.mT.contiguous().mT)]


def test_products_match_float64(openblas: None) -> None:
    rng = np.random.default_rng(0)
    for e, m, k, n in [(4, 256, 23, 256), (2, 1, 256, 256), (2, 256, 256, 1), (3, 6, 256, 64), (1, 17, 5, 3)]:
        for a, b in layouts(e, m, k, n, rng):
            got = gemm.bmm(a, b)
            want = torch.bmm(a.double(), b.double())
            assert got.shape == (e, m, n) and got.dtype == torch.float32
            torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-4)


def test_gradients_match_torch() -> None:
    rng = np.random.default_rng(1)
    bias = torch.from_numpy(rng.standard_normal((3, 8, 1), dtype=np.float32)).requires_grad_()
    a = torch.from_numpy(rng.standard_normal((3, 8, 5), dtype=np.float32)).requires_grad_()
    x = torch.from_numpy(rng.standard_normal((3, 5, 40), dtype=np.float32)).requires_grad_()
    upstream = torch.from_numpy(rng.standard_normal((3, 8, 40), dtype=np.float32))
    ours = torch.autograd.grad((gemm.baddbmm(bias, a, x) * upstream).sum(), (bias, a, x))
    theirs = torch.autograd.grad((torch.baddbmm(bias.double(), a.double(), x.double()) * upstream).sum(), (bias, a, x))
    for got, want in zip(ours, theirs):
        torch.testing.assert_close(got.double(), want.double(), rtol=1e-5, atol=1e-4)


def test_a_product_over_one_term_is_numpy_s_bit_for_bit(openblas: None) -> None:
    """k = 1 (the critics' Q head in the backward) is a multiplication, not a BLAS call: the same
    bits as NumPy's matmul, signed zeros and underflows included, in every layout."""
    rng = np.random.default_rng(5)
    for e, m, n in [(2, 256, 256), (1, 256, 64), (3, 1, 40), (2, 40, 1), (2, 17, 5)]:
        a = rng.standard_normal((e, m, 1), dtype=np.float32)
        b = rng.standard_normal((e, 1, n), dtype=np.float32)
        a.flat[::3] = 0.0
        b.flat[::4] *= np.float32(1e-30)  # products that underflow to a signed zero
        a.flat[1::5] = np.float32(-1e-20)
        b.flat[2::7] = -0.0
        x0, y0 = torch.from_numpy(a), torch.from_numpy(b)
        for x, y in [(x0, y0), (x0.mT.contiguous().mT, y0), (x0, y0.mT.contiguous().mT),
                     (x0.mT.contiguous().mT, y0.mT.contiguous().mT)]:
            want = np.matmul(x.numpy(), y.numpy())
            got = gemm.bmm(x, y).numpy()
            assert np.array_equal(got.view(np.int32), want.view(np.int32)), (e, m, n, x.stride(), y.stride())


def test_relu_backward_is_torch_s_in_every_layout() -> None:
    """`gemm.relu_` against `torch.relu_`: the same output and, for an upstream gradient laid out
    like the output or transposed to it, the same gradient, bit for bit, in the same layout."""
    rng = np.random.default_rng(3)
    for shape in [(2, 64, 48), (48, 64)]:
        x = torch.from_numpy(rng.standard_normal(shape, dtype=np.float32))
        up = torch.from_numpy(rng.standard_normal(shape, dtype=np.float32))
        for xs in (x, x.mT.contiguous().mT):
            for ups in (up, up.mT.contiguous().mT):
                results = []
                for relu in (gemm.relu_, torch.relu_):
                    leaf = xs.clone().requires_grad_()
                    out = relu(leaf * 1.0)  # relu_ acts in place on a non-leaf
                    (grad,) = torch.autograd.grad(out, leaf, ups)
                    results.append((out.detach(), grad))
                (ours, our_grad), (theirs, their_grad) = results
                assert torch.equal(ours, theirs) and torch.equal(our_grad, their_grad)
                assert our_grad.stride() == their_grad.stride()


@pytest.mark.parametrize("algo", ["td3", "ma-sac"])
def test_updates_with_torch_s_relu_give_the_same_bits(algo: str, monkeypatch: pytest.MonkeyPatch) -> None:
    ours = trained(1, algo)
    monkeypatch.setattr(gemm, "relu_", torch.relu_)
    theirs = trained(1, algo)
    for name in ours:
        assert np.array_equal(ours[name], theirs[name]), name


def trained(threads: int, algo: str = "ma-td3", updates: int = 6) -> dict[str, np.ndarray]:
    gemm.set_threads(threads)
    buf = random_replay(17, 6, 1.0, 2000, "cpu")
    # big enough that the members' products do spread over the threads (gemm._PARALLEL_MIN_FLOPS)
    cfg = resolve(algo, actors=1 if algo in ("td3", "sac") else 2, hidden=(128, 128), batch_size=128, seed=4)
    agent = MultiActorAgent(cfg, EnvSpec(17, 6, (1.0,) * 6), "cpu")
    sample = agent.sampler(buf)
    for _ in range(updates):
        agent.update(sample())
    state = agent.state_dict()
    return {f"{net}.{name}": t.numpy().copy() for net in ("actor", "critic", "critic_target")
            for name, t in state[net].items()}


@pytest.mark.parametrize("kernels", ["chain", "openblas"])
@pytest.mark.parametrize("algo", ["ma-td3", "ma-sac", "td3"])
def test_the_same_bits_for_every_thread_count(algo: str, kernels: str, request: pytest.FixtureRequest) -> None:
    if kernels == "openblas":
        request.getfixturevalue("openblas")
    assert 2 * 128 ** 3 >= gemm._PARALLEL_MIN_FLOPS
    one, two, three = trained(1, algo), trained(2, algo), trained(3, algo)
    for name in one:
        assert np.array_equal(one[name], two[name]) and np.array_equal(one[name], three[name]), name


def test_the_batch_call_gives_numpy_s_bits() -> None:
    """OpenBLAS's `sgemm_batch` over two threads (`gemm._Batch`) against NumPy's matmul, one
    product a call, in every layout the layers make: the same bits above its small-matrix bound,
    refused (nothing computed) at or below it."""
    batch = gemm._batch()
    if batch is None:
        pytest.skip("this NumPy's BLAS has no sgemm_batch")
    rng = np.random.default_rng(2)
    for e, m, k, n in [(2, 256, 23, 256), (4, 128, 128, 128), (3, 256, 256, 64), (2, 100, 100, 100), (2, 96, 17, 64)]:
        for a, b in layouts(e, m, k, n, rng):
            an, bn = a.expand(e, -1, -1).numpy(), b.expand(e, -1, -1).numpy()
            want = np.stack([np.matmul(an[i], bn[i]) for i in range(e)])
            got = np.full((e, m, n), np.nan, np.float32)
            used = batch.run([(an[i:i + 1], bn[i:i + 1], got[i:i + 1]) for i in range(e)], 2)
            assert used == (m * n * k > batch.SMALL), (e, m, k, n)
            assert np.array_equal(got, want) if used else np.isnan(got).all()
    # OpenBLAS is back on one thread: a product it would split now runs whole
    x = rng.standard_normal((512, 512), dtype=np.float32)
    assert np.array_equal(x @ x.T.copy(), gemm_one_thread(x))


def gemm_one_thread(x: np.ndarray) -> np.ndarray:
    code = ("import sys, numpy as np, mam_core; x = np.frombuffer(sys.stdin.buffer.read(), np.float32)"
            ".reshape(512, 512); sys.stdout.buffer.write((x @ x.T.copy()).tobytes())")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, input=x.tobytes(), capture_output=True, timeout=60)
    return np.frombuffer(out.stdout, np.float32).reshape(512, 512)


def test_no_product_is_a_row_major_nn_call(monkeypatch: pytest.MonkeyPatch, openblas: None) -> None:
    """Every operand pair an update hands to BLAS: at least one is transposed in BLAS's terms
    (OpenBLAS would run row-major N·N products in its AVX-512 kernel on AVX-512 CPUs)."""
    seen: list[tuple[bool, bool]] = []
    mm = gemm._mm

    def recording(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
        seen.append((gemm.row_major(a), gemm.row_major(b)))
        mm(a, b, out)

    monkeypatch.setattr(gemm, "_mm", recording)
    trained(1, updates=2)
    assert len(seen) > 20 and (True, True) not in seen


def test_the_kernels_a_process_computes_with() -> None:
    """Portable arithmetic: the chain kernels by default, `MAM_PORTABLE_GEMM=openblas` pinned OpenBLAS,
    `mkl` torch's own GEMMs in MKL's COMPATIBLE branch; a name it does not know is an error."""
    code = ("import mam_core; from mam_core import arithmetic; "
            "print(arithmetic.portable_gemm(), arithmetic.status()['gemm'])")
    env = {k: v for k, v in os.environ.items() if k not in arithmetic.PINS and k != arithmetic.GEMM_ENV}
    for asked, want in (("", ["True", "chain"]), ("openblas", ["True", "openblas-haswell"]),
                        ("mkl", ["False", "mkl-compatible"])):
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                             env=dict(env, **{arithmetic.GEMM_ENV: asked, arithmetic.ARITHMETIC_ENV: "portable"}))
        assert out.stdout.split() == want, (asked, out.stderr)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         env=dict(env, **{arithmetic.GEMM_ENV: "blis", arithmetic.ARITHMETIC_ENV: "portable"}))
    assert out.returncode != 0 and "MAM_PORTABLE_GEMM='blis': give one of chain, openblas, mkl" in out.stderr


@pytest.mark.slow
def test_a_run_whose_learner_uses_other_threads_equals_the_reference(tmp_path) -> None:
    """`mam run` with `learner_threads = 2` (its GEMMs over two threads, products big enough to
    spread) against `run_reference` in this process at one: the same evaluations and policy."""
    from mam_core.reference import run_reference
    from tests.e2e import mam, unique_run
    from tests.test_exact import _record, _same_params

    assert gemm.threads() == 1 and 2 * 128 * 128 * 64 >= gemm._PARALLEL_MIN_FLOPS
    config = tmp_path / "threads.toml"
    config.write_text("learner_threads = 2\n")
    flags = dict(hidden=(128, 128), batch_size=64, start_steps=60, compete_every=60, eliminate_at=180, workers=3,
                 actors=2, eval_episodes=1, eval_every=60)
    run_dir = tmp_path / "run"
    mam("run", "--config", str(config), "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", "240",
        "--workers", "3", "--actors", "2", "--start-steps", "60", "--compete-every", "60", "--eliminate-at", "180",
        "--eval-episodes", "1", "--eval-every", "60", "--hidden", "128,128", "--batch-size", "64", "--seed", "5",
        "--run", unique_run("threads"), "--run-dir", str(run_dir), timeout=300)
    assert json.loads((run_dir / "config.json").read_text())["learner_threads"] == 2
    got = _record(run_dir)
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=5, **flags), 240)
    assert got["summary"]["exact"] is True and got["summary"]["survivor"] == ref.survivor
    assert got["evals"] == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert _same_params(got["params"], ref.policy)


def test_the_warm_up_changes_no_bits() -> None:
    """OpenBLAS, each process cold (its threads' first products): TD3 updates with and without the
    warm-up product (`MAM_GEMM_WARM`), on one and on two threads, give the same parameters."""
    code = ("import sys, hashlib, mam_core, numpy as np; from tests.test_gemm import trained; "
            "p = trained(int(sys.argv[1]), 'td3', updates=3); "
            "print(hashlib.sha256(b''.join(p[k].tobytes() for k in sorted(p))).hexdigest())")
    digests = set()
    for warm in ("0", "1"):
        for threads in ("1", "2"):
            out = subprocess.run([sys.executable, "-c", code, threads], cwd=ROOT, capture_output=True, text=True,
                                 timeout=120, env=dict(os.environ, **{gemm.WARM_ENV: warm,
                                                                      arithmetic.GEMM_ENV: "openblas"}))
            assert out.returncode == 0, out.stderr[-2000:]
            digests.add(out.stdout.split()[-1])
    assert len(digests) == 1, digests
