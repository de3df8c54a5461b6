/* A DDM record's crc32 and tag (ddm/wire_kernel.c), for the ddm's kernels. */
#ifndef REDISTRO_WIRE_H
#define REDISTRO_WIRE_H

#include "../kernels.h"

#define TAG_SIZE 32

/* A codec record (CODEC in ddm/wire_layout.py), read: the key, and the
 * layout of the records it seals (the tag covers [0, body) and follows it;
 * the crc32, a u4, at crc_at). */
typedef struct {
    const uint8_t *key;
    size_t key_len;
    int64_t body, crc_at;
} Codec;

/* The codec record at p, checked (else an error is set, 0). */
int codec_read(const uint8_t *p, Codec *c);
/* The crc32 of a record's body, its own field left out. */
uint32_t codec_crc(const Codec *c, const uint8_t *record);
/* out = HMAC-SHA256(key, data[0:n]); 0 when libcrypto fails (an error is set). */
int codec_tag(const Codec *c, const uint8_t *data, size_t n, uint8_t out[TAG_SIZE]);
/* A sealed record's checksum and tag are sound: 0; 2 the checksum, 3 the
 * tag (compared in constant time), -1 libcrypto failed (an error is set). */
int codec_check(const Codec *c, const uint8_t *record);
/* Write a record's checksum and tag (0 when libcrypto fails). */
int codec_seal(const Codec *c, uint8_t *record);

#endif
