/*
 * A DDM record's crc32 and its HMAC-SHA256 tag (their reference:
 * ddm/record.py, Python's zlib and hmac), from zlib and libcrypto, linked.
 *
 * The tag is libcrypto's HMAC through EVP_MAC. A MAC context keyed once per
 * key is kept (a process holds one or two keys; the cache holds 16) and
 * re-initialized for each record with its key kept (EVP_MAC_init with no
 * key), which spares the key's two padded blocks per record. Every caller
 * holds the GIL, which serializes the cache.
 */
#include "wire.h"

#include <openssl/core_names.h>
#include <openssl/evp.h>
#include <zlib.h>

#define KEY_MAX WIRE_CODEC_KEY__LEN
#define CACHED 16

typedef struct {
    uint8_t key[KEY_MAX];
    size_t key_len;
    EVP_MAC_CTX *ctx;
} Keyed;

static Keyed CACHE[CACHED];
static int NEXT_EVICT, LAST_HIT;
static EVP_MAC *HMAC_SHA256;

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

/* A MAC context keyed with c's key (NULL: an error is set). */
static EVP_MAC_CTX *keyed(const Codec *c) {
    Keyed *k = &CACHE[LAST_HIT];
    if (k->ctx != NULL && k->key_len == c->key_len && memcmp(k->key, c->key, c->key_len) == 0)
        return k->ctx;
    for (int i = 0; i < CACHED; i++) {
        k = &CACHE[i];
        if (k->ctx != NULL && k->key_len == c->key_len &&
            memcmp(k->key, c->key, c->key_len) == 0) {
            LAST_HIT = i;
            return k->ctx;
        }
    }
    if (HMAC_SHA256 == NULL && (HMAC_SHA256 = EVP_MAC_fetch(NULL, "HMAC", NULL)) == NULL)
        return crypto_error("EVP_MAC_fetch(HMAC)"), NULL;
    EVP_MAC_CTX *ctx = EVP_MAC_CTX_new(HMAC_SHA256);
    if (ctx == NULL)
        return crypto_error("EVP_MAC_CTX_new"), NULL;
    char digest[] = "SHA256";
    OSSL_PARAM params[] = {
        OSSL_PARAM_construct_utf8_string(OSSL_MAC_PARAM_DIGEST, digest, 0),
        OSSL_PARAM_construct_end(),
    };
    /* (an empty key is a key: libcrypto wants a non-NULL pointer for it) */
    static const uint8_t none[1] = {0};
    if (!EVP_MAC_init(ctx, c->key_len ? c->key : none, c->key_len, params)) {
        EVP_MAC_CTX_free(ctx);
        return crypto_error("EVP_MAC_init"), NULL;
    }
    int i = NEXT_EVICT;
    NEXT_EVICT = (NEXT_EVICT + 1) % CACHED;
    k = &CACHE[i];
    EVP_MAC_CTX_free(k->ctx); /* (NULL: nothing) */
    memcpy(k->key, c->key, c->key_len);
    k->key_len = c->key_len;
    k->ctx = ctx;
    LAST_HIT = i;
    return ctx;
}

int codec_tag(const Codec *c, const uint8_t *data, size_t n, uint8_t out[TAG_SIZE]) {
    EVP_MAC_CTX *ctx = keyed(c);
    size_t len = 0;
    if (ctx == NULL)
        return 0;
    if (!EVP_MAC_init(ctx, NULL, 0, NULL) || !EVP_MAC_update(ctx, data, n) ||
        !EVP_MAC_final(ctx, out, &len, TAG_SIZE) || len != TAG_SIZE)
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
