"""The paper's user study (Sec. "User Study"), simulated: a kitchen robot assembles sandwich orders.

**Task.** 12 ingredients; an order is an ordered list of 3-6 distinct ingredients. The robot is a *step
policy*: input = the counter as it stands (one-hot step index, multi-hot of what is placed, one-hot of
the last ingredient placed), output = logits over the 12 ingredients and "done". A roll-out is greedy
decoding from the empty counter until "done" or 6 ingredients; it is correct only if the whole order
matches exactly, as in the paper. Why a step policy rather than a sequence model: it is the paper's
pi(u | x, k) with the counter as the state x, it is a plain MLP checkpoint that prop's MLP adapter loads
unchanged (prop keys ``nn.Linear`` layers of a feed-forward checkpoint), and its roll-out is the robot's
closed loop (state -> pick -> new state). One order is its teacher-forced states: one row per pick plus
the final "done" (4-7 rows).

**Our reading of the paper.** The paper trains each method on the unified dataset {(k_user, o_user)} U
{(k_1, o_1), ..., (k_N, o_N)}; prop personalizes a *pretrained* checkpoint. So:
- the base checkpoint pi* is an MLP trained to make the house sandwich (the general objective J*); it
  knows no user;
- PRoP = prop's multi-user personalization of that base (Eq. 7 via Eq. 8, ``personalize_checkpoint``
  with one (data, KeySource) pair per user) for the N earlier users (the default dataset) plus the
  participants; nothing in the library was missing. ``PRoP`` feeds the paper's raw key bits,
  ``PRoP-hashed`` prop's default hashed key code;
- keys: every user's username and generated password go through prop's passphrase KDF
  (``prop_cli.core.key_files.passphrase_bits``, scrypt) with the deployment's salt, 32 bits, as the paper's
  "bit-represented keys" of 32 bits. One salt per repetition (a deployment; the bundles record it
  in their manifests); seeded, so reruns match (a real deployment draws it with ``keys.new_salt``);
- the MLP and CVAE baselines (``baselines``) are trained from scratch on the same unified dataset with
  the same Eq. 8 key sampling, house-sandwich targets from the base for every other key (distillation),
  sized to PRoP's parameter count;
- a key outside the unified dataset (random, one bit off) has no order of its own: its correct order
  is the house sandwich, what pi* makes.

**Protocols and metrics.** Each participant's three roll-outs: (A) their key, a uniform random key and
their key with one bit flipped (Sec. "Experimental Setup"); (B) their key and two earlier users' keys
(Sec. "Participants and Procedure"). Score (Eq. us-score, best 3) counts roll-outs that give the key's
order; Privacy (Eq. us-priv, best 0) counts the user's key not giving their order plus every other
key giving it. A repetition's value is the mean over its participants; tables give mean +- s.e. over
repetitions and Welch's t-test (as in ``table``) of each PRoP variant against each baseline.

**Deviation, forced by the budget.** The paper trained three policies per participant. Here all
participants of a repetition join *one* bundle per method with the N earlier users (prop's multi-user
bundle): 4 trainings per repetition instead of 48, so 10 repetitions and the capacity sweep fit in 10
minutes. A participant's bundle therefore holds N + 12 users, not N + 1 (harder, not easier);
``per_participant=True`` trains one bundle per participant, the paper's protocol, to check the
difference (RESULTS.md gives both).

**Run time.** Repetitions share nothing (each has its own salt, people, base and seeds), so the full run
spreads them over two worker processes (``Settings.workers``, ``--workers``) with the same results.

**Methods** are entries of ``METHODS``: a name and a function that trains on a cohort and returns a
policy ``(x, key bits) -> logits``; another method is one more entry. ``SEALED`` runs sealed bundles
(``--seal``, participants added with ``add-user``).
"""

from __future__ import annotations

import math
import multiprocessing
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from examples import save_npz
from examples.reproduce import baselines, common, table
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_files import passphrase_bits

INGREDIENTS = (
    "white bread", "rye bread", "ham", "turkey", "cheddar", "swiss",
    "lettuce", "tomato", "pickles", "onion", "mayo", "mustard",
)  # fmt: skip
N_INGREDIENTS = len(INGREDIENTS)
DONE = N_INGREDIENTS  # the action that ends an order
N_ACTIONS = N_INGREDIENTS + 1
MIN_LEN, MAX_LEN = 3, 6
HOUSE = tuple(INGREDIENTS.index(i) for i in ("white bread", "ham", "cheddar", "lettuce", "mayo"))
STATE_DIM = (MAX_LEN + 1) + N_INGREDIENTS + (N_INGREDIENTS + 1)  # step, placed, last (or none)
KEY_BITS = 32  # the paper's key size for the study
SALT_BYTES = 16
# K1 radius of Eq. 8. The trainer refuses users closer than 2 * radius; with 32-bit keys and up to 140
# users, radius 2 (keys >= 4 bits apart) is the largest that almost never needs a new password.
HAMMING_RADIUS = 2
ROWS_PER_USER = 8
DEMO_COPIES = 10  # each order's rows repeated: prop holds out 20% for its report, all picks must train
BASE_HIDDEN = 32
ENCODER_HIDDEN = 64
METRICS = ("score", "privacy")  # best 3 / best 0
SEED = 20_250


@dataclass(frozen=True)
class Settings:
    reps: int = 10
    participants: int = 12
    main: int = 16  # earlier users in the default dataset of the main table
    sweep: tuple[int, ...] = (8, 16, 32, 64, 128)
    reps_at: dict = field(default_factory=dict)  # fewer repetitions where the budget forces it
    prop_steps: int = 300
    prop_steps_per_user: float = 4.0
    baseline_steps: int = 400
    baseline_steps_per_user: float = 4.0
    lr: float = 1e-2
    base_steps: int = 200
    per_participant: bool = False
    workers: int = 1  # processes, one thread each; repetitions are independent, so results do not change

    def reps_for(self, n: int) -> int:
        return min(self.reps, self.reps_at.get(n, self.reps))


FULL = Settings(workers=2)  # 10 repetitions at every N, on the 2 cores
QUICK = Settings(
    reps=2, participants=3, main=4, sweep=(4, 8), prop_steps=30, prop_steps_per_user=0,
    baseline_steps=30, baseline_steps_per_user=0, base_steps=60,
)  # fmt: skip


# ---- the task --------------------------------------------------------------------------------------


def encode(t: np.ndarray, placed: np.ndarray, last: np.ndarray) -> np.ndarray:
    """States of K counters: step t (K,), placed multi-hot (K, I), last pick (K,) with I = none."""
    k = len(t)
    x = np.zeros((k, STATE_DIM), np.float32)
    x[np.arange(k), t] = 1.0
    x[:, MAX_LEN + 1 : MAX_LEN + 1 + N_INGREDIENTS] = placed
    x[np.arange(k), MAX_LEN + 1 + N_INGREDIENTS + last] = 1.0
    return x


def demonstration(order: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The teacher-forced (state, pick) rows of one order, ending with "done"."""
    n = len(order) + 1
    placed = np.zeros((n, N_INGREDIENTS), np.float32)
    last = np.full(n, N_INGREDIENTS)
    for t in range(1, n):
        placed[t] = placed[t - 1]
        placed[t, order[t - 1]] = 1.0
        last[t] = order[t - 1]
    return encode(np.arange(n), placed, last), np.array([*order, DONE], np.int64)


Policy = Callable[[torch.Tensor, np.ndarray], torch.Tensor]  # (x (B, d), bits (K, n)) -> (K, B, C)


@torch.no_grad()
def rollout(policy: Policy, bits: np.ndarray) -> list[tuple[int, ...]]:
    """Greedy roll-out of every key from the empty counter, all keys in lock-step."""
    k = len(bits)
    placed = np.zeros((k, N_INGREDIENTS), np.float32)
    last = np.full(k, N_INGREDIENTS)
    orders: list[list[int]] = [[] for _ in range(k)]
    alive = np.ones(k, bool)
    diag = np.arange(k)
    for t in range(MAX_LEN + 1):
        x = torch.from_numpy(encode(np.full(k, t), placed, last))
        picks = policy(x, bits)[diag, diag].argmax(-1).numpy()  # key i on its own counter
        for i in np.flatnonzero(alive):
            if picks[i] == DONE or t == MAX_LEN:
                alive[i] = False
            else:
                orders[i].append(int(picks[i]))
                placed[i, picks[i]] = 1.0
                last[i] = picks[i]
        if not alive.any():
            break
    return [tuple(o) for o in orders]


def describe(order: tuple[int, ...]) -> str:
    return " / ".join(INGREDIENTS[i] for i in order)


# ---- people: passwords -> 32-bit keys through prop's KDF ---------------------------------------------


@dataclass
class User:
    name: str
    bits: np.ndarray  # 32 key bits from prop's passphrase KDF
    order: tuple[int, ...]
    passphrase: str = field(repr=False, default="")  # "username\npassword"; in memory only, never written


class Deployment:
    """One repetition: a kitchen with its KDF salt, its participants and a stream of earlier users.

    Earlier users are drawn in a fixed order, so the first N are the same for every N of the sweep,
    and so are the participants: the capacity curve compares like with like.
    """

    def __init__(self, rep: int, participants: int) -> None:
        self.rep = rep
        self.rng = np.random.default_rng((SEED, rep))
        self.salt = self.rng.bytes(SALT_BYTES)
        self.users: list[User] = []  # everyone drawn so far (participants first)
        self.participants = [self._new_user(f"guest-{rep:02d}-{j:02d}") for j in range(participants)]
        self.earlier: list[User] = []

    def earlier_users(self, n: int) -> list[User]:
        while len(self.earlier) < n:
            self.earlier.append(self._new_user(f"user-{self.rep:02d}-{len(self.earlier):03d}"))
        return self.earlier[:n]

    def _new_order(self) -> tuple[int, ...]:
        taken = {u.order for u in self.users} | {HOUSE}
        while True:  # every user's order is their own and not the house sandwich
            n = int(self.rng.integers(MIN_LEN, MAX_LEN + 1))
            order = tuple(int(i) for i in self.rng.permutation(N_INGREDIENTS)[:n])
            if order not in taken:
                return order

    def _new_user(self, name: str) -> User:
        order = self._new_order()
        while True:
            password = "".join(self.rng.choice(list("abcdefghijkmnpqrstuvwxyz23456789"), 10))
            passphrase = f"{name}\n{password}"
            bits = passphrase_bits(passphrase, self.salt, KEY_BITS)
            # prop refuses users closer than 2 * radius (overlapping K1 sets): pick another password.
            if all(int((bits != u.bits).sum()) >= 2 * HAMMING_RADIUS for u in self.users):
                break
        user = User(name, bits, order, passphrase)
        self.users.append(user)
        return user


# ---- what every method trains on --------------------------------------------------------------------


def train_base(seed: int, steps: int) -> nn.Sequential:
    """pi*: makes the house sandwich (the general objective), knows no user."""
    torch.manual_seed(seed)
    model = nn.Sequential(
        nn.Linear(STATE_DIM, BASE_HIDDEN), nn.ReLU(), nn.Linear(BASE_HIDDEN, BASE_HIDDEN), nn.ReLU(),
        nn.Linear(BASE_HIDDEN, N_ACTIONS),
    )  # fmt: skip
    x, y = (torch.from_numpy(a) for a in demonstration(HOUSE))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(steps):
        loss = nn.functional.cross_entropy(model(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return model.eval()


def save_base(base: nn.Module, path: Path) -> None:
    """The pretrained checkpoint as a user has it: safetensors, loaded by prop's MLP adapter."""
    save_file(
        {k: v.contiguous() for k, v in base.state_dict().items()}, str(path), metadata={"activation": "relu"}
    )


def prop_param_count() -> int:
    """Base + key encoder (keyed layers: every linear but the first, prop's default)."""
    base = (STATE_DIM + 1) * BASE_HIDDEN + (BASE_HIDDEN + 1) * BASE_HIDDEN + (BASE_HIDDEN + 1) * N_ACTIONS
    feats = 2 * BASE_HIDDEN
    return base + (KEY_BITS + 1) * ENCODER_HIDDEN + (ENCODER_HIDDEN + 1) * feats


@dataclass
class Cohort:
    """One bundle's worth: the base, the unified dataset's users, their files and the training settings."""

    users: list[User]  # the earlier users (the default dataset) first, then this bundle's participants
    n_earlier: int
    base: nn.Module
    base_path: Path
    general: Path  # the house sandwich's states (fallback inputs)
    files: list[Path]  # one .npz per user
    salt: bytes
    work: Path
    settings: Settings
    seed: int

    def config(self, encoding: str) -> PersonalizeConfig:
        s, n = self.settings, len(self.users)
        return PersonalizeConfig.of(
            steps=int(s.prop_steps + s.prop_steps_per_user * n),
            lr=s.lr,
            user_rows=max(64, ROWS_PER_USER * n),  # every user is seen every step
            encoder_hidden=[ENCODER_HIDDEN],
            key_encoding=encoding,
            hamming_radius=HAMMING_RADIUS,
            eval_random_keys=8,  # the manifest's own report; the study's keys are probed below
            seed=self.seed,
        )

    def baseline_steps(self) -> int:
        s = self.settings
        return int(s.baseline_steps + s.baseline_steps_per_user * len(self.users))


@dataclass
class Fitted:
    policy: Policy
    params: int
    bundle: Path | None = None  # what a prop method wrote (for `prop run` / `prop attack` on it)


def fit_prop(c: Cohort, encoding: str) -> Fitted:
    path = c.work / f"prop-{encoding}.prop"
    bundle = common.run_prop(
        c.base_path,
        [(f, u.bits) for f, u in zip(c.files, c.users)],
        c.general,
        path,
        c.config(encoding),
        kind="passphrase",
        salt=c.salt,
    )
    return Fitted(common.prop_outputs(bundle), common.prop_params(bundle), path)


def fit_baseline(c: Cohort, arch: str) -> Fitted:
    demos = [demonstration(u.order) for u in c.users]
    pool = np.concatenate([demonstration(HOUSE)[0], *(x for x, _ in demos)])
    with torch.no_grad():
        pool_targets = c.base(torch.from_numpy(pool))
    model = baselines.build(arch, STATE_DIM, KEY_BITS, N_ACTIONS, prop_param_count(), c.seed)
    users = [(x, y, u.bits) for (x, y), u in zip(demos, c.users)]
    baselines.train(model, users, pool, pool_targets, "classification", c.config("raw"), c.baseline_steps())
    return Fitted(partial(baselines.outputs, model), baselines.n_params(model))


@dataclass(frozen=True)
class Method:
    name: str
    fit: Callable[[Cohort], Fitted]


SEALED_NAME = "PRoP-sealed"
SEALED_STEPS = 150
SEALED_LR = 0.03


def fit_sealed(c: Cohort) -> Fitted:
    """Sealed bundles (prop personalize --seal): the earlier users in one call, then each participant
    with prop add-user, as the paper's one-participant-at-a-time flow would run; sealed users are
    trained independently, each for ``prop_steps``. A key that opens no record runs the base (the house
    sandwich)."""
    import warnings

    from prop_cli.api import KeySource, add_user, load_bundle, personalize_checkpoint
    from prop_cli.core.payload import Payload
    from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning

    path = c.work / "prop-sealed.prop"
    # Each sealed user trains alone, so the cost grows with users x steps; a user's data is one short
    # demonstration, which SEALED_STEPS at a higher learning rate fits (Score 3.00 at 16 earlier users).
    cfg = c.config("hashed").replace(seal=True, steps=SEALED_STEPS, payload_lr=SEALED_LR)
    first = c.n_earlier or len(c.users)
    users = [(f, KeySource(u.bits, "passphrase")) for f, u in zip(c.files, c.users)]
    personalize_checkpoint(str(c.base_path), users[:first], path, cfg, salt=c.salt)
    for f, key in users[first:]:
        add_user(path, f, key, cfg=cfg)
    bundle = load_bundle(path)

    def run(x: torch.Tensor, bits: np.ndarray) -> torch.Tensor:
        xs = x.numpy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", WrongKeyWarning)  # wrong keys run the base, by design
            return torch.stack([torch.from_numpy(KeyedPolicy(bundle, k, allow_unenrolled=True)(xs))
                                for k in np.atleast_2d(bits)])  # fmt: skip

    payload = baselines.n_params(Payload(bundle.records.spec))
    return Fitted(run, baselines.n_params(bundle.loaded.module) + payload * len(c.users), path)


SEALED: Method | None = Method(SEALED_NAME, fit_sealed)

# The table's rows, in order: PRoP variants first, then the paper's baselines.
METHODS: tuple[Method, ...] = (
    Method(common.PROP, partial(fit_prop, encoding="raw")),
    Method(common.PROP_HASHED, partial(fit_prop, encoding="hashed")),
    *((SEALED,) if SEALED is not None else ()),
    Method("MLP", partial(fit_baseline, arch="MLP")),
    Method("CVAE", partial(fit_baseline, arch="CVAE")),
)
BASELINES = ("MLP", "CVAE")


# ---- the study's roll-outs -------------------------------------------------------------------------


@dataclass
class Probes:
    """Per participant and protocol: three keys and the order each should give."""

    bits: dict[str, np.ndarray]  # protocol -> (P, 3, n)
    targets: dict[str, list[list[tuple[int, ...]]]]  # protocol -> P x 3 orders


Probe = tuple[np.ndarray, tuple[int, ...]]  # a key and the order it should give


def random_and_one_bit_off(p: User, earlier: list[User], taken: set[bytes], rng) -> list[Probe]:
    """Sec. "Experimental Setup": a random key and the user's key one bit off; both should give the house
    sandwich (neither is in the unified dataset)."""
    while True:  # "random" = outside the unified dataset (K - K')
        rand = rng.integers(0, 2, KEY_BITS, dtype=np.uint8)
        if rand.tobytes() not in taken:
            break
    near = p.bits.copy()
    near[rng.integers(KEY_BITS)] ^= 1  # >= 4 bits from every other user: never someone's key
    return [(rand, HOUSE), (near, HOUSE)]


def two_earlier_users(p: User, earlier: list[User], taken: set[bytes], rng) -> list[Probe]:
    """Sec. "Participants and Procedure": two earlier users' keys; each should give that user's order."""
    a, b = rng.choice(len(earlier), 2, replace=False)
    return [(earlier[a].bits, earlier[a].order), (earlier[b].bits, earlier[b].order)]


@dataclass(frozen=True)
class Protocol:
    """The two keys rolled out beside the participant's own (Score and Privacy count three roll-outs)."""

    description: str
    others: Callable[[User, list[User], set[bytes], np.random.Generator], list[Probe]]


# A protocol is one entry; tables, plots and tests iterate over them.
PROTOCOLS: dict[str, Protocol] = {
    "A": Protocol("user key, random key, one bit off", random_and_one_bit_off),
    "B": Protocol("user key, two earlier users' keys", two_earlier_users),
}


def make_probes(participants: list[User], earlier: list[User], bundle_users: list[User], rng) -> Probes:
    taken = {u.bits.tobytes() for u in bundle_users}
    bits: dict[str, list] = {name: [] for name in PROTOCOLS}
    targets: dict[str, list] = {name: [] for name in PROTOCOLS}
    for p in participants:
        for name, proto in PROTOCOLS.items():
            probes = [(p.bits, p.order), *proto.others(p, earlier, taken, rng)]
            bits[name].append([k for k, _ in probes])
            targets[name].append([o for _, o in probes])
    return Probes({k: np.asarray(v, np.uint8) for k, v in bits.items()}, targets)


def study_metrics(got: list[list[tuple]], targets: list[list[tuple]]) -> dict[str, list[float]]:
    """Per participant: Score (Eq. us-score), Privacy (Eq. us-priv) and each roll-out's outcome."""
    out: dict[str, list[float]] = {
        k: [] for k in ("score", "privacy", "own", "other1", "other2", "leak1", "leak2")
    }
    for g, t in zip(got, targets):
        own = g[0] == t[0]
        correct = [g[i] == t[i] for i in (1, 2)]
        leaks = [g[i] == t[0] for i in (1, 2)]
        out["score"].append(float(own + sum(correct)))
        out["privacy"].append(float((not own) + sum(leaks)))
        out["own"].append(float(own))
        out["other1"].append(float(correct[0]))
        out["other2"].append(float(correct[1]))
        out["leak1"].append(float(leaks[0]))
        out["leak2"].append(float(leaks[1]))
    return out


def run_study(policy: Policy, probes: Probes) -> dict[str, dict[str, list[float]]]:
    """All participants' roll-outs of both protocols in one lock-step batch."""
    shapes = {k: v.shape[:2] for k, v in probes.bits.items()}
    flat = np.concatenate([v.reshape(-1, KEY_BITS) for v in probes.bits.values()])
    orders = rollout(policy, flat)
    res, i = {}, 0
    for proto, (p, k) in shapes.items():
        got = [orders[i + j * k : i + (j + 1) * k] for j in range(p)]
        i += p * k
        res[proto] = study_metrics(got, probes.targets[proto])
    return res


# ---- one repetition at one N ------------------------------------------------------------------------


def user_file(work: Path, user: User) -> Path:
    path = work / f"{user.name}.npz"
    if not path.exists():
        x, y = demonstration(user.order)
        save_npz(path, x=np.repeat(x, DEMO_COPIES, 0), y=np.repeat(y, DEMO_COPIES, 0))
    return path


def cohort_runs(dep: Deployment, earlier: list[User], s: Settings) -> list[list[User]]:
    """The participants of each bundle one repetition trains: all together, or one each (the paper's)."""
    if s.per_participant:
        return [[p] for p in dep.participants]
    return [dep.participants]


def make_cohort(
    dep: Deployment, earlier: list[User], new: list[User], base: nn.Module, base_path: Path, work: Path,
    s: Settings,
) -> Cohort:  # fmt: skip
    """The unified dataset of one bundle: the earlier users, then the new participants."""
    general = work / "house.npz"
    if not general.exists():
        save_npz(general, x=np.repeat(demonstration(HOUSE)[0], DEMO_COPIES, 0))
    users = [*earlier, *new]
    d = work / f"n{len(earlier)}-{new[0].name}"
    d.mkdir(parents=True, exist_ok=True)
    files = [user_file(work, u) for u in users]
    return Cohort(users, len(earlier), base, base_path, general, files, dep.salt, d, s, seed=dep.rep)


def run_cell(
    dep: Deployment, n: int, base: nn.Module, base_path: Path, work: Path, s: Settings, log
) -> dict[str, dict]:
    """{method: {protocol: {metric: [per participant]}}} plus "_seconds" and "_params"."""
    earlier = dep.earlier_users(n)
    rng = np.random.default_rng((SEED, dep.rep, n, 1))
    res: dict = {"_seconds": {}, "_params": {}}
    runs = cohort_runs(dep, earlier, s)
    for m in METHODS:
        t0, c0 = time.perf_counter(), time.process_time()
        per_proto: dict = {}
        for new in runs:
            cohort = make_cohort(dep, earlier, new, base, base_path, work, s)
            fitted = m.fit(cohort)
            probes = make_probes(new, earlier, cohort.users, np.random.default_rng(rng.integers(1 << 32)))
            for proto, vals in run_study(fitted.policy, probes).items():
                for k, v in vals.items():
                    per_proto.setdefault(proto, {}).setdefault(k, []).extend(v)
            res["_params"][m.name] = fitted.params
        res[m.name] = per_proto
        res["_seconds"][m.name] = time.perf_counter() - t0
        a = per_proto["A"]
        log(f"  kitchen rep {dep.rep} N={n} {m.name}: score A {np.mean(a['score']):.2f}, privacy A "
            f"{np.mean(a['privacy']):.2f} ({res['_seconds'][m.name]:.1f} s, "
            f"CPU {time.process_time() - c0:.1f} s)")  # fmt: skip
    return res


def log_stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_repetition(
    rep: int, out: Path, s: Settings, sweep: tuple[int, ...], log=log_stderr
) -> dict[int, dict]:
    """One deployment (its salt, people and base) and one cell per N; shares nothing with other reps."""
    dep = Deployment(rep, s.participants)
    work = out / "work" / f"kitchen-{rep}"
    work.mkdir(parents=True, exist_ok=True)
    base = train_base(rep, s.base_steps)
    base_path = work / "base.safetensors"
    save_base(base, base_path)
    return {n: run_cell(dep, n, base, base_path, work, s, log) for n in sweep if rep < s.reps_for(n)}


def _one_thread() -> None:
    torch.set_num_threads(1)  # one thread per worker: a shared thread pool stalls on busy cores


def run(
    out: Path,
    quick: bool,
    reps: int | None = None,
    log=print,
    max_users: int | None = None,
    settings: Settings | None = None,
    per_participant: bool = False,
    workers: int | None = None,
) -> list[dict]:
    s = settings or (QUICK if quick else FULL)
    if reps:
        s = replace(s, reps=reps)
    if per_participant:
        s = replace(s, per_participant=True)
    if workers:
        s = replace(s, workers=workers)
    sweep = tuple(n for n in s.sweep if max_users is None or n <= max_users) or (s.sweep[0],)
    if s.main not in sweep:
        s = replace(s, main=sweep[0])
    t_start = time.perf_counter()
    if s.workers > 1:  # spawn, not fork: a forked torch can hang
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(min(s.workers, s.reps), mp_context=ctx, initializer=_one_thread) as ex:
            per_rep = list(ex.map(partial(run_repetition, out=out, s=s, sweep=sweep), range(s.reps)))
    else:
        per_rep = [run_repetition(rep, out, s, sweep, log) for rep in range(s.reps)]
    cells = {n: [r[n] for r in per_rep if n in r] for n in sweep}
    first = Deployment(0, s.participants)
    wall = time.perf_counter() - t_start
    names = [m.name for m in METHODS]
    params = cells[s.main][0]["_params"]
    main = {
        "name": "kitchen",
        "title": (
            f"Kitchen user study (simulated): {s.participants} participants x {len(cells[s.main])} "
            f"repetitions, {s.main} earlier users, 32-bit keys from passwords"
        ),
        "earlier_users": s.main,
        "participants": s.participants,
        "repetitions": len(cells[s.main]),
        "per_participant": s.per_participant,
        "methods": names,
        "params": params,
        "values": aggregate(cells[s.main], names),
        "seconds": seconds(cells[s.main], names),
        "wall_seconds_all_cells": wall,
        "workers": s.workers,
        "example": {"participant_order": describe(first.participants[0].order), "house": describe(HOUSE)},
    }
    main["markdown"] = markdown(main)
    main["png"] = plot_bars(main, out / "kitchen.png")
    cap = {
        "name": "kitchen_capacity",
        "title": "Kitchen study: Score and Privacy as the number of earlier users grows",
        "sweep": list(sweep),
        "participants": s.participants,
        "repetitions": {str(n): len(cells[n]) for n in sweep},
        "methods": names,
        "values": {str(n): aggregate(cells[n], names) for n in sweep},
        "seconds": {str(n): seconds(cells[n], names) for n in sweep},
    }
    cap["markdown"] = capacity_markdown(cap)
    cap["png"] = plot_capacity(cap, out / "kitchen_capacity.png")
    return [main, cap]


def seconds(cells: list[dict], names: list[str]) -> dict[str, float]:
    return {m: float(sum(c["_seconds"][m] for c in cells)) for m in names}


def aggregate(cells: list[dict], names: list[str]) -> dict:
    """{method: {protocol: {metric: [per-repetition mean over participants]}}}."""
    out: dict = {}
    for m in names:
        for proto in PROTOCOLS:
            for k in cells[0][m][proto]:
                out.setdefault(m, {}).setdefault(proto, {})[k] = [
                    float(np.mean(c[m][proto][k])) for c in cells
                ]
    return out


# ---- tables and figures ------------------------------------------------------------------------------

ARROW = {"score": "↑", "privacy": "↓"}
BEST = {"score": 3, "privacy": 0}


def _ms(values: list[float], digits: int = 2) -> str:
    mu, se = table.mean_se(values)
    return f"{mu:.{digits}f}" if math.isnan(se) else f"{mu:.{digits}f} ± {se:.{digits}f}"


def compare(values: dict, a: str, b: str, proto: str, metric: str) -> tuple[float, float, bool]:
    """(difference of means a - b, Welch p over repetitions, a better)."""
    va, vb = values[a][proto][metric], values[b][proto][metric]
    diff = float(np.mean(va) - np.mean(vb))
    better = diff > 0 if metric == "score" else diff < 0
    return diff, table.welch_p(va, vb), better


def verdict(values: dict, prop: str, proto: str, metric: str) -> str:
    """H1 (score) or H2 (privacy) for one PRoP variant against every baseline."""
    parts, sig_all, better_all, equal_all = [], True, True, True
    for b in BASELINES:
        diff, p, better = compare(values, prop, b, proto, metric)
        better_all &= better
        sig_all &= better and p < table.ALPHA
        equal_all &= abs(diff) < 0.005
        parts.append(f"{diff:+.2f} vs {b} (p = {_p(p)})")
    if sig_all:
        head = "holds"
    elif better_all:
        head = "holds in the means, not significantly against every baseline"
    elif equal_all:
        head = "no difference (the methods tie)"
    else:
        head = "does not hold"
    return f"{head}: " + ", ".join(parts)


def _p(p: float) -> str:
    if math.isnan(p):
        return "n/a"
    return f"{p:.3f}" if p >= 0.001 else f"{p:.1e}"


def comparison_rows(v: dict, names: list[str], first: str = "") -> list[str]:
    """One markdown row per (PRoP variant, baseline): difference of means and Welch p per cell."""
    rows = []
    for a in (m for m in names if table.is_prop(m)):
        for b in BASELINES:
            cells = []
            for proto in PROTOCOLS:
                for k in METRICS:
                    diff, p, better = compare(v, a, b, proto, k)
                    mark = ("*" if better else "!") if p < table.ALPHA else ""
                    cells.append(f"{diff:+.2f}, p = {_p(p)}{mark}")
            rows.append(f"| {first}{a} vs {b} | " + " | ".join(cells) + " |")
    return rows


def markdown(r: dict) -> str:
    v, names = r["values"], r["methods"]
    head = ["method"] + [f"{proto}: {k.capitalize()} {ARROW[k]}" for proto in PROTOCOLS for k in METRICS]
    lines = [
        f"**{r['title']}** — mean ± s.e. over repetitions of the mean over participants; Score best 3, "
        "Privacy best 0",
        "",
        "; ".join(f"Protocol {k}: {p.description}" for k, p in PROTOCOLS.items()) + ".",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for m in names:
        cells = [_ms(v[m][proto][k]) for proto in PROTOCOLS for k in METRICS]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Welch's t-test over repetitions (p; `*` = PRoP variant significantly better at p < {table.ALPHA}, "
        "`!` = significantly worse):",
        "",
        "| comparison | " + " | ".join(head[1:]) + " |",
        "|" + "---|" * len(head),
    ]
    lines += comparison_rows(v, names)
    props = [m for m in names if table.is_prop(m)]
    lines += [
        "",
        "What each roll-out gave (share of participants): own = their key gave their order; slot 2 / 3 = "
        "the other two keys gave *their* correct order (A: the house sandwich; B: that earlier user's "
        "order); leak = the other key gave the participant's order.",
        "",
        "| method | protocol | own ↑ | slot 2 ↑ | slot 3 ↑ | leak slot 2 ↓ | leak slot 3 ↓ |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in names:
        for proto in PROTOCOLS:
            x = v[m][proto]
            cells = [_ms(x[k]) for k in ("own", "other1", "other2", "leak1", "leak2")]
            lines.append(f"| {m} | {proto} | " + " | ".join(cells) + " |")
    lines += ["", "Hypotheses (difference of means, PRoP variant minus baseline; Welch p):"]
    for a in props:
        for proto in PROTOCOLS:
            lines.append(f"- {a}, protocol {proto}: H1 (Score) {verdict(v, a, proto, 'score')}.")
            lines.append(f"- {a}, protocol {proto}: H2 (Privacy) {verdict(v, a, proto, 'privacy')}.")
    lines += [
        "",
        "- Parameters: " + ", ".join(f"{m} {n}" for m, n in r["params"].items())
        + "; training seconds over all repetitions: "
        + ", ".join(f"{m} {s:.0f}" for m, s in r["seconds"].items()),
        f"- House sandwich (what keys outside the dataset should get): {r['example']['house']}; "
        f"participant 1 of repetition 1 ordered: {r['example']['participant_order']}.",
        "- " + ("One bundle per participant (the paper's protocol)." if r["per_participant"] else
                f"All {r['participants']} participants of a repetition share one bundle per method with "
                f"the {r['earlier_users']} earlier users."),
    ]  # fmt: skip
    if SEALED_NAME not in names:
        lines.append(f"- {SEALED_NAME}: not run (the slot `kitchen.SEALED` is empty).")
    return "\n".join(lines)


def capacity_markdown(r: dict) -> str:
    names = r["methods"]
    lines = [f"**{r['title']}** — {r['participants']} participants per repetition, mean ± s.e.", ""]
    for k in METRICS:
        head = ["earlier users", "reps"] + [f"{m} {p}" for m in names for p in PROTOCOLS]
        lines += [
            f"{k.capitalize()} {ARROW[k]} (best {BEST[k]}), protocols A and B:",
            "",
            "| " + " | ".join(head) + " |",
            "|" + "---|" * len(head),
        ]
        for n in r["sweep"]:
            v = r["values"][str(n)]
            cells = [str(n), str(r["repetitions"][str(n)])]
            cells += [_ms(v[m][p][k]) for m in names for p in PROTOCOLS]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    head = [f"{proto}: {k.capitalize()} {ARROW[k]}" for proto in PROTOCOLS for k in METRICS]
    lines += [
        "PRoP variants against the baselines at each size (difference of means, Welch p over repetitions; "
        "`*` / `!` = significantly better / worse):",
        "",
        "| earlier users | comparison | " + " | ".join(head) + " |",
        "|---|" + "---|" * (len(head) + 1),
    ]
    for n in r["sweep"]:
        lines += comparison_rows(r["values"][str(n)], names, first=f"{n} | ")
    lines.append("")
    fewer = [n for n in r["sweep"] if r["repetitions"][str(n)] < max(r["repetitions"].values())]
    if fewer:
        lines.append(
            "Fewer repetitions at " + ", ".join(map(str, fewer)) + " earlier users: the 10-minute budget."
        )
    return "\n".join(lines)


def _colour(i: int, name: str) -> str:
    return f"C{table.ORDER.index(name)}" if name in table.ORDER else f"C{5 + i}"


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _figure(r: dict, path: Path, panel, title: str) -> Path | None:
    """A (metric x protocol) grid; ``panel(ax, metric, protocol)`` draws one and returns its (mean, s.e.)
    pairs, from which the y axis is zoomed to the data (Score near its best of 3, Privacy near 0)."""
    plt = _plt()
    if plt is None:
        return None
    fig, axes = plt.subplots(len(METRICS), len(PROTOCOLS), figsize=(8.5, 5.4), squeeze=False)
    for i, k in enumerate(METRICS):
        for j, proto in enumerate(PROTOCOLS):
            ax = axes[i][j]
            drawn = panel(ax, k, proto)
            if k == "score":
                ax.set_ylim(max(0.0, min(2.0, min(mu - se for mu, se in drawn) - 0.1)), 3.05)
            else:
                ax.set_ylim(-0.02, min(3.0, max(0.5, max(mu + se for mu, se in drawn) + 0.1)))
            ax.set_title(f"protocol {proto}: {PROTOCOLS[proto].description}", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{k.capitalize()} {ARROW[k]} (best {BEST[k]}; axis zoomed)", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _stat(values: list[float]) -> tuple[float, float]:
    mu, se = table.mean_se(values)
    return mu, 0.0 if math.isnan(se) else se


def plot_bars(r: dict, path: Path) -> Path | None:
    """Bars per method with s.e. whiskers, one panel per (metric, protocol); marks as in ``table``."""
    names, v = r["methods"], r["values"]

    def panel(ax, k: str, proto: str) -> list[tuple[float, float]]:
        drawn = []
        for x, m in enumerate(names):
            mu, se = _stat(v[m][proto][k])
            drawn.append((mu, se))
            ax.bar(x, mu, yerr=se, color=_colour(x, m), capsize=3)
            tests = [compare(v, m, b, proto, k) for b in BASELINES] if table.is_prop(m) else []
            if tests and all(p < table.ALPHA for _, p, _ in tests) and len({t[2] for t in tests}) == 1:
                mark = "*" if tests[0][2] else "!"
                ax.text(x, mu + se, mark, ha="center", va="bottom", fontsize=11, weight="bold")
        ax.set_xticks(range(len(names)), names, fontsize=7, rotation=20)
        return drawn

    title = r["title"] + "\n* / ! = PRoP variant significantly better / worse than both baselines"
    return _figure(r, path, panel, title)


def plot_capacity(r: dict, path: Path) -> Path | None:
    names, sweep = r["methods"], r["sweep"]
    xs = [math.log2(n) for n in sweep]

    def panel(ax, k: str, proto: str) -> list[tuple[float, float]]:
        drawn = []
        for x, m in enumerate(names):
            stats = [_stat(r["values"][str(n)][m][proto][k]) for n in sweep]
            drawn += stats
            shift = 0.05 * (x - (len(names) - 1) / 2)  # overlapping lines stay visible at the ceiling
            ax.errorbar(
                [v + shift for v in xs], [s[0] for s in stats], yerr=[s[1] for s in stats],
                fmt="o-", color=_colour(x, m), label=m, capsize=3,
            )  # fmt: skip
        ax.set_xticks(xs, [f"{n}\n({r['repetitions'][str(n)]} reps)" for n in sweep], fontsize=7)
        if k == METRICS[-1]:
            ax.set_xlabel("earlier users in the default dataset", fontsize=8)
        if (k, proto) == (METRICS[0], next(iter(PROTOCOLS))):
            ax.legend(fontsize=7)
        return drawn

    return _figure(r, path, panel, r["title"])
