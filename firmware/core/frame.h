/* The DAQ frame of docs/daq-protocol.md, version 1: 38 bytes, little-endian.
 *
 *   0 sync A5 5A | 2 version | 3 flags | 4 u32 counter | 8 i32[6] counts | 32 u16 latch | 34 i16 temperature
 *   | 36 u16 CRC-16/CCITT-FALSE over bytes 2..35
 *
 * Byte for byte what acquire/daq.py's encode_frames writes for the same sample (tests/test_firmware.py). */
#ifndef FW_FRAME_H
#define FW_FRAME_H

#include <stdint.h>

#define FW_FRAME_SIZE 38
#define FW_FRAME_VERSION 1
#define FW_SYNC0 0xA5u
#define FW_SYNC1 0x5Au
#define FW_CHANNELS 6

#define FW_FLAG_PPS 0x01u    /* PPS edge seen during this sample period */
#define FW_FLAG_LATCH 0x02u  /* latch valid (only with FW_FLAG_PPS) */
#define FW_FLAG_TEMP 0x04u   /* temperature valid */

#define FW_COUNTS_MIN (-8388608L)  /* signed 24-bit ADC range */
#define FW_COUNTS_MAX 8388607L

/* One sample period as the sampling interrupt saw it. */
typedef struct {
    uint32_t counter;                 /* sample index, modulo 2^32 */
    int32_t counts[FW_CHANNELS];      /* gyro x, y, z, accel x, y, z (body RFU), signed 24-bit */
    uint16_t latch;                   /* PPS position in 1/65536 of the period after the previous clock edge */
    int16_t temp_cc;                  /* centi-degrees C */
    uint8_t flags;                    /* FW_FLAG_* */
} fw_sample;

/* Write the frame of s to out. Counts outside the 24-bit range are saturated to it; the latch is written
 * only with FW_FLAG_LATCH and FW_FLAG_PPS set (0 otherwise), the temperature only with FW_FLAG_TEMP, as the
 * host encoder does. */
void fw_frame_build(const fw_sample *s, uint8_t out[FW_FRAME_SIZE]);

/* A 24-bit two's-complement ADC word (in the low 24 bits of raw) as int32. */
int32_t fw_sext24(uint32_t raw);

#endif
