#include "gpio.h"

#include "regs.h"

void gpio_config(uint32_t port, unsigned pin, unsigned mode, unsigned af)
{
    GPIO_AFR(port, pin / 8u) = (GPIO_AFR(port, pin / 8u) & ~(0xFu << (4u * (pin % 8u)))) | (af << (4u * (pin % 8u)));
    GPIO_OSPEEDR(port) |= 3u << (2u * pin);
    GPIO_PUPDR(port) &= ~(3u << (2u * pin));
    GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << (2u * pin))) | (mode << (2u * pin));
}

void gpio_write(uint32_t port, unsigned pin, int high)
{
    GPIO_BSRR(port) = high ? (1u << pin) : (1u << (pin + 16u));
}
