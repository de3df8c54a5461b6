/*
 * A DDM record's crc32 and its HMAC-SHA256 tag (their reference:
 * ddm/record.py, Python's zlib and hmac), from zlib and libcrypto, linked.
 *
 * The tag is HMAC (RFC 2104) over libcrypto's SHA-256 through its EVP digest
 * API. For each key (a process holds one or two; the cache holds 16) the
 * inner and outer states, SHA-256 of the padded key, are computed once and
 * kept as digest contexts; a record copies each (EVP_MD_CTX_copy_ex) and
 * goes on from it, as libcrypto's own HMAC does inside. Its EVP_MAC front
 * costs on OpenSSL 3.0 about 3 us more per record with the caches cold, as
 * a node woken every cycle finds them (docs/PERFORMANCE.md). Every caller
 * holds the GIL, which serializes the cache.
 */
#include "wire.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <zlib.h>

#define KEY_MAX WIRE_CODEC_KEY__LEN
#define CACHED 16
#define BLOCK 64 /* SHA-256's block: the HMAC key's padded length */

typedef struct {
    uint8_t key[KEY_MAX];
    size_t key_len;
    EVP_MD_CTX *inner, *outer; /* SHA-256 of (key ^ ipad), of (key ^ opad) */
} Keyed;

static Keyed CACHE[CACHED];
static int NEXT_EVICT, LAST_HIT;
static EVP_MD *SHA256_MD;
static EVP_MD_CTX *WORK;

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
static int padded(EVP_MD_CTX *ctx, const uint8_t k[BLOCK], uint8_t pad) {
    uint8_t block[BLOCK];
    for (int i = 0; i < BLOCK; i++)
        block[i] = k[i] ^ pad;
    int ok = EVP_DigestInit_ex2(ctx, SHA256_MD, NULL) && EVP_DigestUpdate(ctx, block, BLOCK);
    OPENSSL_cleanse(block, BLOCK);
    return ok;
}

/* The cache's entry for c's key, its states made on a miss (NULL: an error is set). */
static Keyed *keyed(const Codec *c) {
    Keyed *k = &CACHE[LAST_HIT];
    if (k->inner != NULL && k->key_len == c->key_len && memcmp(k->key, c->key, c->key_len) == 0)
        return k;
    for (int i = 0; i < CACHED; i++) {
        k = &CACHE[i];
        if (k->inner != NULL && k->key_len == c->key_len &&
            memcmp(k->key, c->key, c->key_len) == 0) {
            LAST_HIT = i;
            return k;
        }
    }
    if (SHA256_MD == NULL && (SHA256_MD = EVP_MD_fetch(NULL, "SHA256", NULL)) == NULL)
        return crypto_error("EVP_MD_fetch(SHA256)"), NULL;
    if (WORK == NULL && (WORK = EVP_MD_CTX_new()) == NULL)
        return crypto_error("EVP_MD_CTX_new"), NULL;
    /* the key as a block: hashed first when longer than one (RFC 2104) */
    uint8_t kb[BLOCK] = {0};
    unsigned int n = 0;
    if (c->key_len > BLOCK) {
        if (!EVP_Digest(c->key, c->key_len, kb, &n, SHA256_MD, NULL))
            return crypto_error("SHA-256 of the key"), NULL;
    } else {
        memcpy(kb, c->key, c->key_len);
    }
    EVP_MD_CTX *inner = EVP_MD_CTX_new(), *outer = EVP_MD_CTX_new();
    int ok = inner && outer && padded(inner, kb, 0x36) && padded(outer, kb, 0x5c);
    OPENSSL_cleanse(kb, BLOCK);
    if (!ok) {
        EVP_MD_CTX_free(inner);
        EVP_MD_CTX_free(outer);
        return crypto_error("HMAC key states"), NULL;
    }
    int i = NEXT_EVICT;
    NEXT_EVICT = (NEXT_EVICT + 1) % CACHED;
    k = &CACHE[i];
    EVP_MD_CTX_free(k->inner); /* (NULL: nothing) */
    EVP_MD_CTX_free(k->outer);
    memcpy(k->key, c->key, c->key_len);
    k->key_len = c->key_len;
    k->inner = inner;
    k->outer = outer;
    LAST_HIT = i;
    return k;
}

int codec_tag(const Codec *c, const uint8_t *data, size_t n, uint8_t out[TAG_SIZE]) {
    Keyed *k = keyed(c);
    if (k == NULL)
        return 0;
    uint8_t in[TAG_SIZE];
    unsigned int a = 0, b = 0;
    int ok = EVP_MD_CTX_copy_ex(WORK, k->inner) && EVP_DigestUpdate(WORK, data, n) &&
             EVP_DigestFinal_ex(WORK, in, &a) && EVP_MD_CTX_copy_ex(WORK, k->outer) &&
             EVP_DigestUpdate(WORK, in, TAG_SIZE) && EVP_DigestFinal_ex(WORK, out, &b);
    OPENSSL_cleanse(in, TAG_SIZE);
    if (!ok || a != TAG_SIZE || b != TAG_SIZE)
        return crypto_error("HMAC-SHA256");
    return 1;
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
