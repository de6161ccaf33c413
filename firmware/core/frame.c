#include "frame.h"

#include "crc16.h"
#include "le.h"

int32_t fw_sext24(uint32_t raw)
{
    raw &= 0xFFFFFFu;
    return (raw & 0x800000u) ? (int32_t)(raw | 0xFF000000u) : (int32_t)raw;
}

static int32_t saturate24(int32_t v)
{
    return v < FW_COUNTS_MIN ? (int32_t)FW_COUNTS_MIN : v > FW_COUNTS_MAX ? (int32_t)FW_COUNTS_MAX : v;
}

void fw_frame_build(const fw_sample *s, uint8_t out[FW_FRAME_SIZE])
{
    uint8_t flags = s->flags & (FW_FLAG_PPS | FW_FLAG_LATCH | FW_FLAG_TEMP);
    if (!(flags & FW_FLAG_PPS))
        flags &= (uint8_t)~FW_FLAG_LATCH;
    out[0] = FW_SYNC0;
    out[1] = FW_SYNC1;
    out[2] = FW_FRAME_VERSION;
    out[3] = flags;
    fw_put32(out + 4, s->counter);
    for (int i = 0; i < FW_CHANNELS; i++)
        fw_put32(out + 8 + 4 * i, (uint32_t)saturate24(s->counts[i]));
    fw_put16(out + 32, (flags & FW_FLAG_LATCH) ? s->latch : 0);
    fw_put16(out + 34, (flags & FW_FLAG_TEMP) ? (uint16_t)s->temp_cc : 0);
    fw_put16(out + 36, fw_crc16(FW_CRC16_INIT, out + 2, 34));
}
