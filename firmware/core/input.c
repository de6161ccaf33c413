#include "input.h"

#include <string.h>

#include "crc16.h"
#include "le.h"

void fw_input_init(fw_input *p)
{
    memset(p, 0, sizeof *p);
}

/* Drop bytes from the front until buf starts with a (possibly partial) sync pair. */
static void resync(fw_input *p, uint32_t from)
{
    uint32_t i = from;
    while (i < p->len && !(p->buf[i] == FW_INPUT_SYNC0 && (i + 1 == p->len || p->buf[i + 1] == FW_INPUT_SYNC1)))
        i++;
    p->skipped += i;
    memmove(p->buf, p->buf + i, p->len - i);
    p->len -= i;
}

static void decode(const uint8_t *b, fw_input_record *rec)
{
    rec->flags = b[2];
    for (int i = 0; i < FW_CHANNELS; i++)
        rec->counts[i] = fw_sext24(fw_get24(b + 3 + 3 * i));
    rec->sample_ticks = fw_get32(b + 21);
    rec->pps_ticks = fw_get32(b + 25);
    rec->temp_cc = (int16_t)fw_get16(b + 29);
}

fw_input_result fw_input_feed(fw_input *p, uint8_t byte, fw_input_record *rec)
{
    p->buf[p->len++] = byte;
    if (p->len <= 2) {
        resync(p, 0);
        return FW_INPUT_MORE;
    }
    if (p->len < FW_INPUT_SIZE)
        return FW_INPUT_MORE;
    if (fw_crc16(FW_CRC16_INIT, p->buf + 2, FW_INPUT_SIZE - 4) == fw_get16(p->buf + FW_INPUT_SIZE - 2)) {
        decode(p->buf, rec);
        p->len = 0;
        return FW_INPUT_RECORD;
    }
    p->bad_crc++;
    resync(p, 1);
    return FW_INPUT_BAD;
}
