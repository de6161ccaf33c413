/* Reading MCAP records in C: the record walk of drive/chunks.py and the chunk reader of drive/native.py; and
 * the byte layout of messages.Packed.prefixed, for writing them (their docstrings give the contracts). Built
 * with the package (setup.py) and called through ctypes; it needs no Python headers. libzstd and zlib-ng are not
 * linked: the caller passes the addresses of the functions the installed zstandard and zlib_ng packages export,
 * so the kernels use the very builds python-zstandard and zlib_ng use.
 *
 * A record is an opcode byte, a little-endian u64 body length and the body (MCAP). Every read is bounds-checked
 * against the buffer; a length that does not fit (or has its top bit set) ends the walk there.
 */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

typedef size_t (*zstd_decompress_fn)(void *dctx, void *dst, size_t dst_cap, const void *src, size_t src_len);
typedef unsigned (*zstd_is_error_fn)(size_t code);
typedef uint32_t (*crc32_fn)(uint32_t crc, const uint8_t *buf, uint32_t len);

enum { OK, CODEC, SIZE, CRC };        /* what is wrong with a chunk: native.OK, CODEC, SIZE, CRC */
enum { NONE, ZSTD };                  /* a chunk's compression: native.NONE, ZSTD */
enum { OP_SCHEMA = 3, OP_CHANNEL = 4, OP_MESSAGE = 5 };

static int64_t le(const uint8_t *p, int width)
{
    uint64_t v = 0;
    for (int b = 0; b < width; b++)
        v |= (uint64_t)p[b] << (8 * b);
    return (int64_t)v;
}

/* The records of buf[pos:n], at most cap of them: opcode, body start, body length into ops, starts, lengths.
 * Returns the number walked; *end is the end of the last complete record walked. */
int64_t fieldlog_walk(const uint8_t *buf, int64_t n, int64_t pos, int64_t cap, uint8_t *ops, int64_t *starts,
                      int64_t *lengths, int64_t *end)
{
    int64_t k = 0;
    while (k < cap && pos + 9 <= n) {
        int64_t length = le(buf + pos + 1, 8);
        if (length < 0 || length > n - pos - 9)
            break;
        ops[k] = buf[pos];
        starts[k] = pos + 9;
        lengths[k] = length;
        k++;
        pos += 9 + length;
    }
    *end = pos;
    return k;
}

/* Chunks j < m of src (comp[j], at[j], length[j], size[j], crc[j]: see native.read_chunks), in turn:
 * decompressed into stage, checked, walked, and the messages on channels marked in want (65536 bytes) copied
 * with the schema and channel records into out. Message rows go to rec (k x 4: record start in out, body length,
 * log_time, publish_time) and ch (k), schema and channel rows to defs (nd x 3: opcode, body start in out, body
 * length); the caller sizes them for the bytes (a kept message record is 31 bytes at least, a kept definition 23).
 * res[0..4] = first bad chunk or -1, what is wrong (OK ...), bytes of out used, k, nd. */
void fieldlog_read_chunks(zstd_decompress_fn decompress, zstd_is_error_fn is_error, crc32_fn crc32, void *dctx,
                          const uint8_t *src, int64_t m, const uint8_t *comp, const int64_t *at,
                          const int64_t *length, const int64_t *size, const int64_t *crc, uint8_t *stage,
                          uint8_t *out, const uint8_t *want, int64_t *rec, uint16_t *ch, int64_t *defs,
                          int64_t *res)
{
    int64_t k = 0, nd = 0, o = 0;
    res[0] = -1;
    res[1] = OK;
    for (int64_t j = 0; j < m; j++) {
        int64_t n;
        if (comp[j] == ZSTD) {
            size_t r = decompress(dctx, stage, (size_t)size[j], src + at[j], (size_t)length[j]);
            if (is_error(r)) {
                res[0] = j;
                res[1] = CODEC;
                break;
            }
            n = (int64_t)r;
        } else {
            n = length[j];
            if (n == size[j])
                memcpy(stage, src + at[j], (size_t)n);
        }
        if (n != size[j]) {
            res[0] = j;
            res[1] = SIZE;
            break;
        }
        if (crc[j] != 0 && crc32(0, stage, (uint32_t)n) != (uint32_t)crc[j]) {
            res[0] = j;
            res[1] = CRC;
            break;
        }
        int64_t pos = 0;
        while (pos + 9 <= n) {  /* the chunk's records, while they are in the cache */
            int64_t body = le(stage + pos + 1, 8);
            if (body < 0 || body > n - pos - 9)
                break;
            uint8_t op = stage[pos];
            int keep = (op == OP_SCHEMA || op == OP_CHANNEL) && body >= 14;  /* defined inside: 14, 16 bytes */
            if (op == OP_MESSAGE && body >= 22) {  /* channel u16, sequence u32, log_time, publish_time */
                uint16_t c = (uint16_t)le(stage + pos + 9, 2);
                if (want[c]) {
                    rec[4 * k] = o;
                    rec[4 * k + 1] = body;
                    rec[4 * k + 2] = le(stage + pos + 15, 8);
                    rec[4 * k + 3] = le(stage + pos + 23, 8);
                    ch[k] = c;
                    k++;
                    memcpy(out + o, stage + pos, (size_t)(9 + body));
                    o += 9 + body;
                }
            } else if (keep) {
                defs[3 * nd] = op;
                defs[3 * nd + 1] = o + 9;
                defs[3 * nd + 2] = body;
                nd++;
                memcpy(out + o, stage + pos, (size_t)(9 + body));
                o += 9 + body;
            }
            pos += 9 + body;
        }
    }
    res[2] = o;
    res[3] = k;
    res[4] = nd;
}

/* out = head 0, message 0, head 1, message 1, ...: the n heads of k bytes (back to back in heads) each in front of
 * its message, message i being src[offsets[i]:offsets[i + 1]] (messages.Packed.prefixed) */
void fieldlog_prefix(int64_t n, int64_t k, const uint8_t *heads, const uint8_t *src, const int64_t *offsets,
                     uint8_t *out)
{
    for (int64_t i = 0; i < n; i++) {
        int64_t len = offsets[i + 1] - offsets[i];
        memcpy(out, heads + i * k, (size_t)k);
        out += k;
        memcpy(out, src + offsets[i], (size_t)len);
        out += len;
    }
}
