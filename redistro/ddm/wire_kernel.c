/*
 * A DDM record's crc32 and its HMAC-SHA256 tag (their reference:
 * ddm/record.py, Python's zlib and hmac), from zlib and libcrypto, linked.
 *
 * The tag is HMAC (RFC 2104) over libcrypto's SHA-256 (SHA256_Init,
 * SHA256_Update, SHA256_Final: <openssl/sha.h>, its SHA256_CTX a plain
 * struct declared there). For each key (a process holds one or two; the
 * cache holds 16) the inner and outer states, SHA-256 of the padded key,
 * are computed once and kept; a record copies each (a struct assignment)
 * and goes on from it, as libcrypto's own HMAC does inside. OpenSSL 3
 * marks these functions deprecated in favour of its EVP API, whose copy of
 * a digest context frees, allocates and cleanses on every record: with the
 * caches cold, as a node woken every cycle finds them, EVP_MD_CTX_copy_ex
 * costs 1.5-2.3 us more per check and seal, and EVP_MAC about 3 us more
 * (docs/PERFORMANCE.md). Every caller holds the GIL, which serializes the
 * cache.
 */
#define OPENSSL_SUPPRESS_DEPRECATED /* SHA256_*: see above */
#include "wire.h"

#include <openssl/crypto.h>
#include <openssl/sha.h>
#include <zlib.h>

#define KEY_MAX WIRE_CODEC_KEY__LEN
#define CACHED 16
#define BLOCK SHA256_CBLOCK /* SHA-256's block: the HMAC key's padded length */

typedef struct {
    uint8_t key[KEY_MAX];
    size_t key_len;
    int made;
    SHA256_CTX inner, outer; /* SHA-256 of (key ^ ipad), of (key ^ opad) */
} Keyed;

static Keyed CACHE[CACHED];
static int NEXT_EVICT, LAST_HIT;

int codec_read(const uint8_t *p, Codec *c) {
    c->key = p + WIRE_CODEC_KEY;
    c->key_len = ld_u32(p + WIRE_CODEC_KEY_LEN);
    c->body = (int64_t)ld_u64(p + WIRE_CODEC_BODY);
    c->crc_at = (int64_t)ld_u64(p + WIRE_CODEC_CRC_AT);
    if (c->key_len > KEY_MAX || c->body <= 0 || c->body > (1 << 20) || c->crc_at < 0 ||
        c->crc_at + 4 > c->body) {
        PyErr_Format(PyExc_ValueError,
                     "a codec of a %zu-byte key (at most %d), a %lld-byte body, the crc at %lld "
                     "(inside the body)",
                     c->key_len, KEY_MAX, (long long)c->body, (long long)c->crc_at);
        return 0;
    }
    return 1;
}

uint32_t codec_crc(const Codec *c, const uint8_t *r) {
    uLong crc = crc32(0L, r, (uInt)c->crc_at);
    return (uint32_t)crc32(crc, r + c->crc_at + 4, (uInt)(c->body - c->crc_at - 4));
}

static int crypto_error(const char *what) {
    PyErr_Format(PyExc_RuntimeError, "libcrypto: %s failed", what);
    return 0;
}

/* ctx := SHA-256 begun on (k ^ pad), k a block-sized key. */
static int padded(SHA256_CTX *ctx, const uint8_t k[BLOCK], uint8_t pad) {
    uint8_t block[BLOCK];
    for (int i = 0; i < BLOCK; i++)
        block[i] = k[i] ^ pad;
    int ok = SHA256_Init(ctx) && SHA256_Update(ctx, block, BLOCK);
    OPENSSL_cleanse(block, BLOCK);
    return ok;
}

static int same_key(const Keyed *k, const Codec *c) {
    return k->made && k->key_len == c->key_len && memcmp(k->key, c->key, c->key_len) == 0;
}

/* The cache's entry for c's key, its states made on a miss (NULL: an error is set). */
static Keyed *keyed(const Codec *c) {
    Keyed *k = &CACHE[LAST_HIT];
    if (same_key(k, c))
        return k;
    for (int i = 0; i < CACHED; i++) {
        if (same_key(&CACHE[i], c)) {
            LAST_HIT = i;
            return &CACHE[i];
        }
    }
    /* the key as a block: hashed first when longer than one (RFC 2104) */
    uint8_t kb[BLOCK] = {0};
    if (c->key_len > BLOCK) {
        if (SHA256(c->key, c->key_len, kb) == NULL)
            return crypto_error("SHA-256 of the key"), NULL;
    } else {
        memcpy(kb, c->key, c->key_len);
    }
    int i = NEXT_EVICT;
    NEXT_EVICT = (NEXT_EVICT + 1) % CACHED;
    k = &CACHE[i];
    OPENSSL_cleanse(k, sizeof *k); /* (nothing of an evicted key stays) */
    k->made = padded(&k->inner, kb, 0x36) && padded(&k->outer, kb, 0x5c);
    OPENSSL_cleanse(kb, BLOCK);
    if (!k->made) {
        OPENSSL_cleanse(k, sizeof *k);
        return crypto_error("HMAC key states"), NULL;
    }
    memcpy(k->key, c->key, c->key_len);
    k->key_len = c->key_len;
    LAST_HIT = i;
    return k;
}

int codec_tag(const Codec *c, const uint8_t *data, size_t n, uint8_t out[TAG_SIZE]) {
    Keyed *k = keyed(c);
    if (k == NULL)
        return 0;
    uint8_t in[TAG_SIZE];
    SHA256_CTX w = k->inner;
    int ok = SHA256_Update(&w, data, n) && SHA256_Final(in, &w);
    w = k->outer;
    ok = ok && SHA256_Update(&w, in, TAG_SIZE) && SHA256_Final(out, &w);
    OPENSSL_cleanse(in, TAG_SIZE);
    return ok ? 1 : crypto_error("HMAC-SHA256");
}

int codec_check(const Codec *c, const uint8_t *r) {
    if (ld_u32(r + c->crc_at) != codec_crc(c, r))
        return 2;
    uint8_t tag[TAG_SIZE];
    if (!codec_tag(c, r, (size_t)c->body, tag))
        return -1;
    return CRYPTO_memcmp(tag, r + c->body, TAG_SIZE) ? 3 : 0;
}

int codec_seal(const Codec *c, uint8_t *r) {
    st_u32(r + c->crc_at, codec_crc(c, r));
    return codec_tag(c, r, (size_t)c->body, r + c->body);
}

/* -- the module's functions: each takes a plan of "wire" (its codec) -- */

static int wire_args(PyObject *const *args, Py_ssize_t nargs, const char *usage, Codec *c,
                     Py_buffer *b, int flags) {
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "%s", usage);
        return 0;
    }
    PlanObject *pl = plan_arg(args[0], "wire");
    if (pl == NULL || !codec_read(U8(pl, 0), c))
        return 0;
    return PyObject_GetBuffer(args[1], b, flags) == 0;
}

/* wire_tag(plan, data) -> the 32-byte HMAC-SHA256 of data under the codec's key. */
static PyObject *wire_tag(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    Codec c;
    Py_buffer b;
    if (!wire_args(args, nargs, "wire_tag(plan, data)", &c, &b, PyBUF_SIMPLE))
        return NULL;
    uint8_t out[TAG_SIZE];
    int ok = codec_tag(&c, b.buf, (size_t)b.len, out);
    PyBuffer_Release(&b);
    return ok ? PyBytes_FromStringAndSize((const char *)out, TAG_SIZE) : NULL;
}

/* wire_seal(plan, record): the record's crc32 and tag written in place. */
static PyObject *wire_seal(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    Codec c;
    Py_buffer b;
    if (!wire_args(args, nargs, "wire_seal(plan, record)", &c, &b, PyBUF_WRITABLE))
        return NULL;
    if (b.len != c.body + TAG_SIZE) {
        PyErr_Format(PyExc_ValueError, "wire_seal: a record of %lld bytes, got %zd",
                     (long long)c.body + TAG_SIZE, b.len);
        PyBuffer_Release(&b);
        return NULL;
    }
    int ok = codec_seal(&c, b.buf);
    PyBuffer_Release(&b);
    if (!ok)
        return NULL;
    Py_RETURN_NONE;
}

/* wire_verify(plan, record) -> 0 sound, 1 wrong size, 2 checksum, 3 tag. */
static PyObject *wire_verify(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    Codec c;
    Py_buffer b;
    if (!wire_args(args, nargs, "wire_verify(plan, record)", &c, &b, PyBUF_SIMPLE))
        return NULL;
    int why = b.len != c.body + TAG_SIZE ? 1 : codec_check(&c, b.buf);
    PyBuffer_Release(&b);
    return why < 0 ? NULL : PyLong_FromLong(why);
}

static const Signature WIRE_SIGNATURES[] = {
    {"wire", ARGS(REC("codec", 'B', WIRE_CODEC__N))},
};

static PyMethodDef WIRE_METHODS[] = {
    {"wire_tag", (PyCFunction)(void (*)(void))wire_tag, METH_FASTCALL,
     "HMAC-SHA256 of data under the codec's key (libcrypto)."},
    {"wire_seal", (PyCFunction)(void (*)(void))wire_seal, METH_FASTCALL,
     "Write a record's crc32 and tag."},
    {"wire_verify", (PyCFunction)(void (*)(void))wire_verify, METH_FASTCALL,
     "Check a record: 0 sound, 1 size, 2 checksum, 3 tag."},
    {NULL, NULL, 0, NULL},
};

const KernelSet WIRE_KERNELS = {WIRE_SIGNATURES, 1, WIRE_METHODS};
