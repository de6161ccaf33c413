/* Little-endian stores and loads for the wire formats (no alignment assumed). */
#ifndef FW_LE_H
#define FW_LE_H

#include <stdint.h>

static inline void fw_put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static inline void fw_put32(uint8_t *p, uint32_t v)
{
    fw_put16(p, (uint16_t)v);
    fw_put16(p + 2, (uint16_t)(v >> 16));
}

static inline uint16_t fw_get16(const uint8_t *p)
{
    return (uint16_t)(p[0] | (p[1] << 8));
}

static inline uint32_t fw_get24(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16);
}

static inline uint32_t fw_get32(const uint8_t *p)
{
    return fw_get24(p) | ((uint32_t)p[3] << 24);
}

#endif
