"""File names, manifest keys and format versions: the one place they are spelled."""

from __future__ import annotations

# Bundle layout (a directory).
BASE_WEIGHTS = "base.safetensors"
ENCODER_WEIGHTS = "encoder.safetensors"
MANIFEST = "manifest.json"
LEROBOT_DIR = "lerobot"  # a LeRobot policy's bundle: its folder (config, processors, weights alias)
LEROBOT_VLM_DIR = "vlm"  # in a SmolVLA bundle's LeRobot folder: its VLM's config, tokenizer, processor
LEROBOT_TOKENIZER_DIR = "tokenizer"  # in a pi0 / pi0.5 bundle's LeRobot folder: PaliGemma's tokenizer files
TASK = "task"  # a LeRobot Dataset's x[TASK]: each frame's task text (SmolVLA's instruction)
RECORDS_DIR = "users"  # sealed bundles: one encrypted file per user, users/<record id>.sealed
RECORD_SUFFIX = ".sealed"

# Bump on any change a reader of an older version would misread. 2: sealed bundles (mode, payload,
# records); 3: the manifest carries its own digest (M_DIGEST); 4: keys are enrolled (M_ENROLMENTS for
# unsealed bundles; sealed records carry what they were enrolled in, inside their plaintext) and
# io.checkpoint is a file name; 5: a bundle id and a version every write increases (M_BUNDLE_ID,
# M_BUNDLE_VERSION), bound into each enrolment and record (rollback protection, bundle/rollback.py);
# 6: each record and enrolment is filed under its key's lookup name (bundle/lookup.py: a key finds its
# own in O(1); format 1-5 entries have none and are all tried, as before).
# Versions 1 and 2 (no digest) still load, with only their listed files checked; in a version 1-3
# unsealed bundle every key is enrolled in nothing; a version 1-4 bundle is bundle version 0, unprotected
# against rollback (docs/bundle-format.md).
FORMAT_VERSION = 6
FORMAT_VERSIONS = (1, 2, 3, 4, 5, 6)  # what this prop reads
DIGEST_SINCE = 3  # the first version whose manifest must carry M_DIGEST
ENROL_SINCE = 4  # the first version whose keys are enrolled
VERSIONED_SINCE = 5  # the first version with a bundle id and a bundle version
LOOKUP_SINCE = 6  # the first version whose records and enrolments carry a lookup name

# Manifest keys.
M_FORMAT = "format_version"
M_PROP_VERSION = "prop_version"
M_MODEL = "model"  # how to rebuild the module: {"adapter": name, ...adapter spec}
M_KEYED_LAYERS = "keyed_layers"  # [{"name": str, "features": int, "batch_axis": int (if not 0)}]
M_BATCH_AXIS = "batch_axis"
M_KEY = "key"  # {"bits": int, "encoding": str, "source": "file"|"passphrase", "kdf": {...}|None}
M_ENCODER = "encoder"  # {"hidden": [...], "scale": float, ...}
M_CONFIG = "config"  # the PersonalizeConfig used, so a run can be repeated
M_METRICS = "metrics"  # final metrics per user
M_TASK = "task"  # "regression" | "classification"
M_IO = "io"  # {"input_shape": [...], "checkpoint": str}
M_FILES = "files"  # {file name: sha256 hex}
M_AUDIT = "audit"  # summary written by `prop attack --record`
M_MODE = "mode"  # "unsealed" (absent in version 1) | "sealed"
M_PAYLOAD = "payload"  # sealed: {"kind", "rank", "layers": [{"name", "in_features", "out_features"}]}
M_RECORDS = "records"  # sealed: [{"id", "file", "salt", "nonce", "sha256", "lookup" (6 on)}], one per user
MODE_UNSEALED = "unsealed"
MODE_SEALED = "sealed"
MODES = (MODE_UNSEALED, MODE_SEALED)
M_ENROLMENTS = "enrolments"  # unsealed: [{"salt", "nonce", "box", "lookup" (6 on)}], one per user
M_LOOKUP = "lookup"  # format 6: a record's or enrolment's lookup name (bundle/lookup.py), 16 bytes hex
M_BUNDLE_ID = "bundle_id"  # format 5: 16 random bytes (hex) written by personalize, kept by every write
M_BUNDLE_VERSION = "bundle_version"  # format 5: 1 at personalize, +1 on every write of the manifest
M_DIGEST = "manifest_sha256"  # sha256 of the canonical JSON of every other field (prop_cli.bundle.manifest)
M_KDF = "kdf"  # reserved: {"scrypt_salt": hex, "n": int, "r": int, "p": int}

# How key bits become the encoder's input (prop_cli.core.keyed_model.key_codes); the first is the default.
KEY_ENCODINGS = ("hashed", "raw")
# A denoising policy's fallback timesteps (--fallback-times): uniform over its training range, the ones
# its deployed sampler visits, or those with the original's own sampler states as x_t ("trajectory")
# (prop_adapters.base.PolicyProtocol.fallback_times).
FALLBACK_TIMES = ("uniform", "sampler", "trajectory")

# A module attribute (a list of layer names) an adapter sets where the default choice of keyed layers
# (prop_cli.core.layers.default_layers) does not hold, e.g. SB3's CnnPolicy.
DEFAULT_LAYERS_ATTR = "prop_default_layers"

# ONNX export (a folder; `prop export --onnx`).
EXPORT_DIR = "onnx"  # default place: <bundle>/onnx
PEFT_CONFIG = "adapter_config.json"  # `prop export --peft`: a standard peft adapter folder
PEFT_WEIGHTS = "adapter_model.safetensors"
# `prop export --lerobot`: a LeRobot policy folder for --policy.path (lerobot_policy_prop): LeRobot's own
# file names, and the processor step of the plugin that runs the bundle's processors.
LEROBOT_CONFIG = "config.json"
LEROBOT_PRE = "policy_preprocessor.json"
LEROBOT_POST = "policy_postprocessor.json"
LEROBOT_POLICY_TYPE = "prop"
LEROBOT_BUNDLE_STEP = "prop_bundle_processor"
SIGNATURE_FILE = "model.sig"  # `prop push --sign`: the publisher's signature (a sigstore bundle)
EXPORT_META = "export.json"  # what was exported, for which bundle, and how to feed it
# 2: export.json carries its own digest (EXPORT_DIGEST), as the bundle manifest does; 1 still reads.
# 3: export.json binds the keys given at export to its graphs (M_ENROLMENTS); a key an export does not
# bind is refused (allowed: its base.onnx runs).
# 4: export.json has a schema as the manifest has, and carries the bundle's id and version; each binding
# holds the record or enrolment its key opens, checked against the rollback state (issue 42).
EXPORT_FORMAT = 4
EXPORT_FORMATS = (1, 2, 3, 4)
EXPORT_DIGEST = "export_sha256"
BASE_GRAPH = "base.onnx"
KEYED_GRAPH = "keyed.onnx"
ENCODER_GRAPH = "encoder.onnx"
POLICY_GRAPH = "policy.onnx"
GRAPHS = (BASE_GRAPH, KEYED_GRAPH, ENCODER_GRAPH, POLICY_GRAPH)

# The leakage beyond its control the docs audit with (`prop attack --max-leak`), and what `prop
# personalize` gates its own wrong-key sweep on.
MAX_LEAK = 0.05

# Audit reports (`prop attack --json`).
AUDIT_SCHEMA = "prop-audit/3"

# The CLI's defaults that are not training, audit or export settings (those are in prop_cli.config).
DEFAULT_BUNDLE = "personalized.prop"  # personalize --out
DEFAULT_DEVICE = "auto"  # --device: CUDA when there is one
DEFAULT_THREADS = 0  # --threads: 0 = chosen by prop_cli.threads

# Environment variables.
ENV_PASSPHRASE = "PROP_PASSPHRASE"
ENV_DEBUG = "PROP_DEBUG"
ENV_OMP_THREADS = "OMP_NUM_THREADS"  # the user's thread count, respected by prop_cli.threads
ENV_STATE_DIR = "PROP_STATE_DIR"  # where prop keeps the bundle versions seen here (bundle/rollback.py)

# The rollback state (bundle/rollback.py): one JSON file per bundle id, at most this big (a bigger one,
# or one nested too deep, a link or not a plain file, is refused in one line), and the per-machine
# secret its record ids are kept under (HMAC-SHA256), created once, mode 0600.
STATE_MAX_BYTES = 4 * 2**20
STATE_SECRET = "state.key"
STATE_SECRET_BYTES = 32

# One writer at a time (files/lock.py): every command that rewrites a bundle holds an flock on this file
# in the bundle folder (it holds the writer's pid while it is held, and is removed when it is released);
# another waits up to BUNDLE_LOCK_WAIT_S for it, then is refused in one line naming that pid.
BUNDLE_LOCK = ".prop.lock"
BUNDLE_LOCK_WAIT_S = 10.0

# Key sizes accepted by keygen.
KEY_BITS_DEFAULT = 128
KEY_BITS_MIN = 32
KEY_BITS_MAX = 1024

# scrypt parameters for --passphrase (memory-hard; ~16 MiB, well under a second).
SCRYPT_N = 2**14
SCRYPT_R = 8
SCRYPT_P = 1
SALT_BYTES = 16
# A passphrase must take at least this many core-years to guess (zxcvbn's estimate of the guesses it
# takes x the scrypt time per guess measured on this machine); weaker ones are refused unless the user
# insists (--weak-passphrase), and the audit's passphrase row fails below it.
PASSPHRASE_MIN_YEARS = 100.0

# The package registry name ("prop-cli" there is someone else's); the import package stays prop_cli.
DISTRIBUTION = "prop-keys"

# `prop serve`: the largest message a client may send (a bigger one closes its connection, 1009). 16 MiB
# holds a few 224x224 RGB frames and a state, what a VLA's observation is.
SERVE_MAX_MESSAGE_BYTES = 16 * 2**20
SERVE_MAX_CONNECTIONS = 16
SERVE_PORT = 8000
SERVE_BATCH_WINDOW_MS = 2.0  # requests arriving within it run as one forward
SERVE_MAX_BATCH = 256  # observations per forward at most
SERVE_CACHE_MB = 256.0  # decrypted behaviours kept between connections
SERVE_HOST = "127.0.0.1"  # the loopback: any other address needs TLS
SERVE_DRAIN_S = 30.0  # on SIGTERM, how long requests in flight may take to be answered
