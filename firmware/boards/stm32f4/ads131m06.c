#include "ads131m06.h"

#include <string.h>

#include "board.h"
#include "crc16.h"
#include "gpio.h"
#include "spi.h"

#define WORD 3u                        /* bytes per SPI word (24-bit mode) */
#define FRAME_WORDS (2u + FW_CHANNELS) /* status or command, channels, CRC */
#define CMD_RESET 0x0011u
#define CMD_WREG(addr, n) (0x6000u | ((addr) << 7) | ((n) - 1u))
#define REG_CLOCK 0x03u
/* CLOCK: all six channels on (bits 13:8), OSR 8192 (bits 4:2 = 110), high-resolution power mode (10) */
#define CLOCK_500HZ ((0x3Fu << 8) | (6u << 2) | 2u)

static void delay_cycles(uint32_t n)
{
    while (n--)
        __asm volatile("nop");
}

static void frame(const uint16_t *words, unsigned n, uint8_t rx[FRAME_WORDS * WORD])
{
    uint8_t tx[FRAME_WORDS * WORD];
    memset(tx, 0, sizeof tx);
    for (unsigned i = 0; i < n; i++) {   /* a 16-bit command or value fills the top of a 24-bit word */
        tx[WORD * i] = (uint8_t)(words[i] >> 8);
        tx[WORD * i + 1] = (uint8_t)words[i];
    }
    gpio_write(PIN_ADC_CS, 0);
    spi_transfer(tx, rx, sizeof tx);
    gpio_write(PIN_ADC_CS, 1);
}

void ads_init(void)
{
    uint8_t rx[FRAME_WORDS * WORD];
    gpio_write(PIN_ADC_CS, 1);
    gpio_write(PIN_ADC_RESET, 0);       /* hold /RESET low > 2048 CLKIN periods (250 us) */
    delay_cycles(CORE_HZ / 1000u);
    gpio_write(PIN_ADC_RESET, 1);
    delay_cycles(CORE_HZ / 1000u);      /* t_REGACQ after reset */
    const uint16_t wreg[] = {CMD_WREG(REG_CLOCK, 1u), CLOCK_500HZ};
    frame(wreg, 2, rx);
}

int ads_read(int32_t counts[FW_CHANNELS])
{
    static const uint16_t null_cmd[] = {0x0000u};
    uint8_t rx[FRAME_WORDS * WORD];
    frame(null_cmd, 1, rx);
    /* the output CRC covers every word before it; it sits in the top 16 bits of the last word */
    uint16_t crc = fw_crc16(FW_CRC16_INIT, rx, (FRAME_WORDS - 1u) * WORD);
    const uint8_t *c = rx + (FRAME_WORDS - 1u) * WORD;
    if (crc != (uint16_t)((c[0] << 8) | c[1]))
        return -1;
    for (unsigned i = 0; i < FW_CHANNELS; i++) {
        const uint8_t *w = rx + WORD * (1u + i);
        counts[i] = fw_sext24(((uint32_t)w[0] << 16) | ((uint32_t)w[1] << 8) | w[2]);
    }
    return 0;
}
