#include "usart.h"

#include "regs.h"

void usart_init(uint32_t base, uint32_t pclk_hz, uint32_t baud)
{
    USART_CR1(base) = 0;
    /* BRR = pclk / baud with 4 fraction bits: mantissa << 4 | sixteenths, i.e. round(pclk / baud) */
    USART_BRR(base) = (pclk_hz + baud / 2u) / baud;
    USART_CR1(base) = USART_CR1_UE | USART_CR1_TE;
}

void usart_write(uint32_t base, const uint8_t *data, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        while (!(USART_SR(base) & USART_SR_TXE))
            ;
        USART_DR(base) = data[i];
    }
}
